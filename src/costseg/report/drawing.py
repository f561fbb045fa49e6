"""Figures drawn side by side on forked processes, one batch at a time.

Matplotlib holds the GIL while it draws, so threads would take turns; forked processes inherit
the figures' data without pickling it. A batch is an iterable of ``(tag, figure)``, typically a
generator that redraws one figure (e.g. :func:`costseg.report.ternary.ternary_figures`), so
each batch is drawn by one process. Every process takes the next batch until none is left,
writes ``folder/<tag>.png`` and reports the tags and image shapes; the calling process draws
too, then logs every image to TensorBoard in the batches' order. Importing this module imports
neither matplotlib nor TensorBoard, so that drawing can start before this process needs them.
"""

from __future__ import annotations

import multiprocessing
import os
import queue
import signal
import traceback
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Protocol

if TYPE_CHECKING:
    from matplotlib.figure import Figure
    from torch.utils.tensorboard import SummaryWriter


Batch = Iterable[tuple[str, "Figure"]]
Drawn = list[tuple[str, tuple[int, ...]]]  # (tag, (H, W, 3)) of each figure of a batch


class Started(Protocol):
    """Drawing started earlier (a :class:`Drawing`, ``report.early_figures.EarlyFigures``)."""

    def finish(self) -> list[tuple[str, Drawn]]: ...


def save_and_log_all(
    writer: SummaryWriter,
    batches: Sequence[tuple[str, Batch]],
    folder: Path,
    started: Started | None = None,
) -> None:
    """Draw each ``(prefix, batch)`` to ``folder/<tag>.png`` and to TensorBoard as
    ``prefix/<tag>``, on as many processes as there are usable cores; ``started``: batches
    already being drawn, e.g. while the images were evaluated, logged first.

    >>> import tempfile
    >>> from matplotlib.figure import Figure
    >>> from torch.utils.tensorboard import SummaryWriter
    >>> with tempfile.TemporaryDirectory() as d, SummaryWriter(d) as w:
    ...     batches = [("eval", {"empty": Figure(figsize=(1, 1))}.items())]
    ...     save_and_log_all(w, batches, Path(d) / "figures")
    ...     sorted(p.name for p in (Path(d) / "figures").iterdir())
    ['empty.png']
    """
    from costseg.report.tensorboard import log_png

    workers = min(len(os.sched_getaffinity(0)), len(batches)) - 1
    drawn = Drawing(batches, folder, workers).finish()
    for prefix, figures in (started.finish() if started else []) + drawn:
        for tag, shape in figures:
            log_png(writer, f"{prefix}/{tag}", _path(folder, tag).read_bytes(), shape)


class Drawing:
    """``(prefix, batch)`` pairs drawn to ``folder`` by ``workers`` forked processes from now
    on, while this one goes on.

    :meth:`finish` draws the batches that no worker has taken yet in this process and waits
    for the others; without ``fork`` (or workers) it draws them all. :meth:`cancel` stops the
    workers.
    """

    def __init__(self, batches: Sequence[tuple[str, Batch]], folder: Path, workers: int) -> None:
        self.prefixes = [prefix for prefix, _ in batches]
        self.batches, self.folder, self.workers = [b for _, b in batches], folder, []
        if workers < 1 or "fork" not in multiprocessing.get_all_start_methods():
            self.claimed = multiprocessing.Value("i", 0)
            return
        context = multiprocessing.get_context("fork")
        self.claimed, self.reports = context.Value("i", 0), context.Queue()
        args = (self.batches, folder, self.claimed, self.reports)
        self.workers = [
            context.Process(target=_work, args=args, daemon=True) for _ in range(workers)
        ]
        for worker in self.workers:
            worker.start()

    def finish(self) -> list[tuple[str, Drawn]]:
        """``(prefix, tags and image shapes)`` of each batch, in order, once all are drawn."""
        try:
            done = dict(_claim_and_draw(self.batches, self.folder, self.claimed))
            while len(done) < len(self.batches):
                index, outcome = _next_report(self.reports, self.workers)
                if isinstance(outcome, OSError):  # e.g. a full disk: the user's to fix
                    raise outcome
                if isinstance(outcome, str):
                    raise RuntimeError(f"drawing figures failed in a worker process:\n{outcome}")
                done[index] = outcome
        finally:
            self.cancel(timeout=5)
        return [(prefix, done[i]) for i, prefix in enumerate(self.prefixes)]

    def cancel(self, timeout: float = 0) -> None:
        """Wait up to ``timeout`` seconds for the workers to end, then stop them."""
        for worker in self.workers:
            worker.join(timeout=timeout)
            if worker.is_alive():
                worker.terminate()


def _draw(batch: Batch, folder: Path) -> Drawn:
    import matplotlib

    from costseg.report.files import render, write_png

    drawn = []
    # A fixed title height: matplotlib's default measures every tick label at each draw to
    # lift the title over ticks at the top, and none of these figures has any.
    with matplotlib.rc_context({"axes.titley": 1.0}):
        for tag, fig in batch:
            image = render(fig)
            write_png(_path(folder, tag), image)
            drawn.append((tag, image.shape))
    return drawn


def _path(folder: Path, tag: str) -> Path:
    return folder / f"{tag.replace('/', '_')}.png"


def _claim_and_draw(batches: Sequence[Batch], folder: Path, claimed):
    """Yield ``(index, drawn)`` of each batch that this process claims, until none is left."""
    while True:
        with claimed.get_lock():
            index = claimed.value
            claimed.value += 1
        if index >= len(batches):
            return
        yield index, _draw(batches[index], folder)


def _work(batches: Sequence[Batch], folder: Path, claimed, reports) -> None:
    """A worker process: report ``(index, drawn)`` per batch, ``(index, OSError)`` or
    ``(index, traceback)``. Ctrl-C is the parent's to handle: it stops the workers."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    index = -1
    try:
        for index, drawn in _claim_and_draw(batches, folder, claimed):
            reports.put((index, drawn))
    except OSError as err:
        reports.put((index, OSError(err.errno, err.strerror, err.filename)))
    except BaseException:
        reports.put((index, traceback.format_exc()))


def _next_report(reports, workers: list) -> tuple[int, Drawn | OSError | str]:
    """The next report; an error report if every worker has ended with reports missing."""
    while True:
        try:
            return reports.get(timeout=1)
        except queue.Empty:
            if not any(worker.is_alive() for worker in workers):
                codes = [worker.exitcode for worker in workers]
                return -1, f"the worker processes ended (exit codes {codes}) with figures undrawn"
