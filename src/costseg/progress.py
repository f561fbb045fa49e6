"""Progress that shows wherever the output goes: a tqdm bar on a terminal, and otherwise (a file,
a pipe, a CI log) one plain line every few percent, so a long job is never silent.

>>> import io
>>> out = io.StringIO()
>>> with Progress(4, "work", every=50, file=out) as bar:
...     for _ in range(4):
...         bar.update()
>>> print(out.getvalue().replace("\\r", ""), end="")  # doctest: +ELLIPSIS
work: 2/4 (50%)...
work: 4/4 (100%)...
"""

from __future__ import annotations

import sys
import time
from collections.abc import Iterable, Iterator
from typing import IO, Any, TypeVar

T = TypeVar("T")


class Progress:
    """Progress towards ``total`` steps.

    Args:
        total: the number of steps (None: unknown; then a line every 100 steps).
        desc: what progresses, at the start of each line.
        initial: steps already done (a resumed training).
        every: percent between two lines when the output is not a terminal.
        file: where to write (default: stderr).
    """

    def __init__(
        self,
        total: int | None,
        desc: str,
        initial: int = 0,
        every: float = 5,
        file: IO[str] | None = None,
    ) -> None:
        self.total, self.desc, self.n, self.every = total, desc, initial, every
        self.file = file or sys.stderr
        self.start, self.start_n, self.shown = time.monotonic(), initial, initial
        self.bar = None
        if getattr(self.file, "isatty", lambda: False)():
            from tqdm import tqdm

            self.bar = tqdm(total=total, desc=desc, initial=initial, file=self.file)

    def update(self, steps: int = 1, postfix: dict[str, Any] | None = None) -> None:
        """Count ``steps`` more (with ``postfix``: values to show, e.g. the loss)."""
        self.update_to(self.n + steps, postfix)

    def update_to(self, n: int, postfix: dict[str, Any] | None = None) -> None:
        """Set the count to ``n``."""
        if self.bar is not None:
            self.bar.update(n - self.n)
            if postfix:
                self.bar.set_postfix(postfix, refresh=False)
        self.n = n
        if self.bar is None and self._due():
            self.shown = n
            print(self._line(postfix), file=self.file, flush=True)

    def close(self) -> None:
        """End the bar (a terminal) or print the last line if it is not printed yet."""
        if self.bar is not None:
            self.bar.close()
        elif self.n != self.shown:
            self.shown = self.n
            print(self._line(None), file=self.file, flush=True)

    def __enter__(self) -> Progress:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _due(self) -> bool:
        if not self.total:
            return self.n - self.shown >= 100
        step = max(1, round(self.total * self.every / 100))
        return self.n // step > self.shown // step or self.n >= self.total > self.shown

    def _line(self, postfix: dict[str, Any] | None) -> str:
        elapsed = time.monotonic() - self.start
        text = f"{self.desc}: {self.n}"
        if self.total:
            text += f"/{self.total} ({100 * self.n / self.total:.0f}%)"
        done = self.n - self.start_n
        text += f", {_clock(elapsed)} elapsed"
        if self.total and done > 0 and self.n < self.total:
            text += f", ~{_clock(elapsed / done * (self.total - self.n))} left"
        if postfix:
            text += ", " + ", ".join(f"{k} {_short(v)}" for k, v in postfix.items())
        return text


def progress(items: Iterable[T], desc: str | None, total: int | None = None) -> Iterator[T]:
    """Yield ``items``, showing progress under ``desc`` (None: silently).

    >>> list(progress(range(3), None))
    [0, 1, 2]
    """
    if desc is None:
        yield from items
        return
    if total is None and hasattr(items, "__len__"):
        total = len(items)  # type: ignore[arg-type]
    with Progress(total, desc) as bar:
        for item in items:
            yield item
            bar.update()


def _clock(seconds: float) -> str:
    minutes, seconds = divmod(int(seconds), 60)
    return (
        f"{minutes // 60}:{minutes % 60:02d}:{seconds:02d}"
        if minutes >= 60
        else (f"{minutes}:{seconds:02d}")
    )


def _short(value: Any) -> str:
    return f"{value:.4g}" if isinstance(value, float) else str(value)
