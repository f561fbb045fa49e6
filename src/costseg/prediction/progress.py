"""Progress of a prediction: tqdm's bar on a terminal, else one line every few percent (logs)."""

from __future__ import annotations

import sys
from typing import TextIO

from tqdm import tqdm

STEP_PERCENT = 5
STEP_ITEMS = 100  # a line every this many items when the total is unknown


class Progress:
    """Counts finished items of ``what`` (images, frames); silent when ``enabled`` is false.

    >>> import io
    >>> out = io.StringIO()
    >>> with Progress("frames", 40, stream=out) as p:
    ...     for _ in range(40):
    ...         p.update()
    >>> out.getvalue().splitlines()[:2]
    ['predict: 2/40 frames (5 %)', 'predict: 4/40 frames (10 %)']
    """

    def __init__(
        self, what: str, total: int | None, enabled: bool = True, stream: TextIO | None = None
    ) -> None:
        self.what, self.total, self.done, self.shown = what, total, 0, 0
        self.stream = stream or sys.stderr
        terminal = stream is None and sys.stderr.isatty()
        self.bar = tqdm(total=total, desc="predict", unit=what) if enabled and terminal else None
        self.lines = enabled and not terminal

    def __enter__(self) -> Progress:
        return self

    def update(self) -> None:
        """One more item done."""
        self.done += 1
        if self.bar is not None:
            self.bar.update()
        elif self.lines:
            self._line()

    def _line(self) -> None:
        if self.total:
            step = self.done * 100 // self.total // STEP_PERCENT
            if step > self.shown or self.done == self.total:
                self.shown = step
                percent = self.done * 100 // self.total
                text = f"predict: {self.done}/{self.total} {self.what} ({percent} %)"
                print(text, file=self.stream, flush=True)
        elif self.done % STEP_ITEMS == 0:
            print(f"predict: {self.done} {self.what}", file=self.stream, flush=True)

    def __exit__(self, *exc) -> None:
        if self.bar is not None:
            self.bar.close()
