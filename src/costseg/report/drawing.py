"""Figures drawn side by side on forked processes, one batch at a time.

Matplotlib holds the GIL while it draws, so threads would take turns; forked processes inherit
the figures' data without pickling it. A batch is an iterable of ``(tag, figure)``, typically a
generator that redraws one figure (e.g. :func:`costseg.report.ternary.ternary_figures`), so
each batch is drawn by one process. Every process takes the next batch until none is left,
writes ``folder/<tag>.png`` and reports the tags and image shapes; the calling process draws
too, then logs every image to TensorBoard in the batches' order.
"""

from __future__ import annotations

import multiprocessing
import os
import queue
import traceback
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import matplotlib
from matplotlib.figure import Figure

from costseg.report.files import png_bytes, render, write_bytes
from costseg.report.tensorboard import log_png

if TYPE_CHECKING:
    from torch.utils.tensorboard import SummaryWriter

Batch = Iterable[tuple[str, Figure]]
Drawn = list[tuple[str, tuple[int, ...]]]  # (tag, (H, W, 3)) of each figure of a batch


def save_and_log_all(
    writer: SummaryWriter,
    batches: Sequence[tuple[str, Batch]],
    folder: Path,
    processes: int | None = None,
) -> None:
    """Draw each ``(prefix, batch)`` to ``folder/<tag>.png`` and to TensorBoard as
    ``prefix/<tag>``, on up to ``processes`` processes (default: the usable cores).

    >>> import tempfile
    >>> from torch.utils.tensorboard import SummaryWriter
    >>> with tempfile.TemporaryDirectory() as d, SummaryWriter(d) as w:
    ...     batches = [("eval", {"empty": Figure(figsize=(1, 1))}.items())]
    ...     save_and_log_all(w, batches, Path(d) / "figures")
    ...     sorted(p.name for p in (Path(d) / "figures").iterdir())
    ['empty.png']
    """
    drawn = draw([batch for _, batch in batches], folder, processes)
    for (prefix, _), figures in zip(batches, drawn, strict=True):
        for tag, shape in figures:
            log_png(writer, f"{prefix}/{tag}", _path(folder, tag).read_bytes(), shape)


def draw(batches: Sequence[Batch], folder: Path, processes: int | None = None) -> list[Drawn]:
    """Write every figure of every batch to ``folder/<tag>.png``; returns each batch's tags and
    image shapes, in order. Runs in this process alone where ``fork`` is not available."""
    processes = min(processes or len(os.sched_getaffinity(0)), len(batches))
    if processes <= 1 or "fork" not in multiprocessing.get_all_start_methods():
        return [_draw(batch, folder) for batch in batches]
    context = multiprocessing.get_context("fork")
    claimed, reports = context.Value("i", 0), context.Queue()
    workers = [
        context.Process(target=_work, args=(batches, folder, claimed, reports), daemon=True)
        for _ in range(processes - 1)
    ]
    for worker in workers:
        worker.start()
    try:
        done = dict(_claim_and_draw(batches, folder, claimed))
        while len(done) < len(batches):
            index, outcome = _next_report(reports, workers)
            if isinstance(outcome, str):
                raise RuntimeError(f"drawing figures failed in a worker process:\n{outcome}")
            done[index] = outcome
    finally:
        for worker in workers:
            worker.join(timeout=5)
            if worker.is_alive():
                worker.terminate()
    return [done[i] for i in range(len(batches))]


def _draw(batch: Batch, folder: Path) -> Drawn:
    drawn = []
    # A fixed title height: matplotlib's default measures every tick label at each draw to
    # lift the title over ticks at the top, and none of these figures has any.
    with matplotlib.rc_context({"axes.titley": 1.0}):
        for tag, fig in batch:
            image = render(fig)
            write_bytes(_path(folder, tag), png_bytes(image))
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
    """A worker process: report ``(index, drawn)`` per batch, or ``(index, traceback)``."""
    index = -1
    try:
        for index, drawn in _claim_and_draw(batches, folder, claimed):
            reports.put((index, drawn))
    except BaseException:
        reports.put((index, traceback.format_exc()))


def _next_report(reports, workers: list) -> tuple[int, Drawn | str]:
    """The next report; an error report if every worker has ended with reports missing."""
    while True:
        try:
            return reports.get(timeout=1)
        except queue.Empty:
            if not any(worker.is_alive() for worker in workers):
                codes = [worker.exitcode for worker in workers]
                return -1, f"the worker processes ended (exit codes {codes}) with figures undrawn"
