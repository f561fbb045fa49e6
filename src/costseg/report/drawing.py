"""Figures drawn side by side in worker processes that cannot inherit a held lock.

Matplotlib holds the GIL while it draws, so threads would take turns. The workers come from the
forkserver (:mod:`costseg.workers`), never from a fork of this process, whose torch thread
pool and threads may hold locks. A job is a picklable callable that returns ``(tag, figure)``
pairs, typically ``functools.partial`` of a generator that redraws one figure (e.g.
:func:`costseg.report.ternary.ternary_figures`) over plain data: NumPy arrays and Python values.
:func:`job` turns the tensors among its arguments into NumPy arrays in this process, so that no
worker runs a torch operation; :meth:`Drawing.submit` refuses a tensor that slipped through.

Each worker takes the next job, writes ``folder/<tag>.png`` for every figure and reports each
one, while the calling process goes on; :meth:`Drawing.finish` returns every job's figures in
the jobs' order. A worker that ends with figures undrawn, or that reports nothing for
:data:`costseg.workers.STALL_SECONDS`, ends the wait with :class:`costseg.workers.Stalled`.
Importing this module imports neither matplotlib nor torch.
"""

from __future__ import annotations

import functools
import io
import multiprocessing
import os
import pickle
import queue
import time
import traceback
from collections.abc import Callable, Iterable
from multiprocessing.reduction import ForkingPickler
from pathlib import Path
from typing import TYPE_CHECKING

from costseg import workers
from costseg.workers import Stalled

if TYPE_CHECKING:
    from matplotlib.figure import Figure


Job = Callable[[], Iterable[tuple[str, "Figure"]]]
Drawn = list[tuple[str, tuple[int, ...]]]  # (tag, (H, W, 3)) of each figure of a job


def job(function: Callable[..., Iterable[tuple[str, Figure]]], *args, **kwargs) -> Job:
    """``function(*args, **kwargs)`` as a job, with every tensor in the arguments (also inside
    lists, tuples and dicts) turned into a NumPy array here (float16 stays float16).

    >>> import torch
    >>> job(dict, a=[torch.ones(2)]).keywords["a"][0].dtype
    dtype('float32')
    """
    return functools.partial(function, *_numpy(args), **_numpy(kwargs))


def _numpy(value):
    if type(value).__module__.startswith("torch"):
        return value.detach().cpu().numpy()
    if isinstance(value, dict):
        return {k: _numpy(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return type(value)(_numpy(v) for v in value)
    return value


class Drawing:
    """``processes`` forkserver processes that draw the jobs :meth:`submit` gives them into
    ``folder``, while this process goes on; :meth:`finish` waits for all of them, a bounded
    wait, and stops the workers; :meth:`cancel` stops them at once."""

    def __init__(self, folder: Path, processes: int) -> None:
        self.folder, self.prefixes = folder, []
        workers.start()
        self.tasks, self.reports = workers.CONTEXT.Queue(), workers.CONTEXT.Queue()
        args = (folder, _Queues(self.tasks, self.reports))
        self.workers = [
            workers.CONTEXT.Process(target=_work, args=args, daemon=True)
            for _ in range(max(1, processes))
        ]
        # each start waits for the forkserver to fork: a bounded wait too
        workers.within(lambda: [w.start() for w in self.workers], "the forkserver")

    def submit(self, prefix: str, drawn_job: Job) -> None:
        """Queue ``drawn_job`` (its figures logged under ``prefix``); it must pickle without a
        tensor (:func:`job` makes one)."""
        self.tasks.put((len(self.prefixes), payload(drawn_job)))
        self.prefixes.append(prefix)

    def finish(self) -> list[tuple[str, Drawn]]:
        """``(prefix, tags and image shapes)`` of each job, in order, once all are drawn."""
        drawn: dict[int, Drawn] = {i: [] for i in range(len(self.prefixes))}
        try:
            for _ in self.workers:
                self.tasks.put(None)  # each worker ends after the jobs queued before it
            pending, at = set(drawn), {}  # at: the job and figure a worker was last heard on
            heard = time.monotonic()
            while pending:
                try:
                    kind, pid, index, value = self.reports.get(timeout=1)
                except queue.Empty:
                    self._check(at, time.monotonic() - heard)
                    continue
                heard, at[pid] = time.monotonic(), (index, value)
                if kind == "figure":
                    drawn[index].append(value)
                elif kind == "done":
                    pending.discard(index)
                elif isinstance(value, OSError):  # e.g. a full disk: the user's to fix
                    raise value
                elif kind == "error":
                    raise RuntimeError(f"drawing figures failed in a worker process:\n{value}")
        except BaseException:
            self.cancel()
            raise
        self.cancel(timeout=5)  # each has taken its None and ends
        return [(prefix, drawn[i]) for i, prefix in enumerate(self.prefixes)]

    def _check(self, at: dict, silent: float) -> None:
        """Raise :class:`Stalled` if a worker ended before the jobs did, or none was heard
        from for :data:`costseg.workers.STALL_SECONDS`."""
        for worker in self.workers:  # one that ended well took its None: others draw
            if worker.exitcode or all(w.exitcode is not None for w in self.workers):
                where = self._where(at.get(worker.pid))
                raise Stalled(
                    f"a figure worker (pid {worker.pid}) ended with exit code {worker.exitcode}"
                    f"{where} before the figures in {self.folder} were drawn"
                )
        if silent > workers.STALL_SECONDS:
            where = "; ".join(f"pid {pid}{self._where(a)}" for pid, a in sorted(at.items()))
            raise Stalled(
                f"the figure workers drew nothing for {silent:.0f} s "
                f"({where or 'none started a job'}); figures in {self.folder} are incomplete"
            )

    def _where(self, at: tuple[int, object] | None) -> str:
        """Where a worker was last heard: after a figure, or in a job (its prefix)."""
        if at is None or at[0] < 0:
            return ""
        prefix, value = self.prefixes[at[0]], at[1]
        return f" after {prefix}/{value[0]}" if isinstance(value, tuple) else f" in {prefix}"

    def cancel(self, timeout: float = 0) -> None:
        """Wait up to ``timeout`` seconds for the workers to end, then stop them."""
        for worker in self.workers:
            worker.join(timeout=timeout)
            if worker.is_alive():
                worker.kill()
                worker.join(timeout=5)
        self.tasks.cancel_join_thread()  # jobs no worker will read must not hold up the exit


def payload(drawn_job: Job) -> bytes:
    """``drawn_job`` as a worker receives it: pickled, refusing any torch object (a worker
    must not run torch)."""
    buffer = io.BytesIO()
    _NoTensors(buffer, protocol=pickle.HIGHEST_PROTOCOL).dump(drawn_job)
    return buffer.getvalue()


class _NoTensors(pickle.Pickler):
    """A pickler that refuses torch objects: a worker must not run torch."""

    def reducer_override(self, obj):
        if type(obj).__module__.startswith("torch"):
            raise TypeError(f"a drawing job carries a {type(obj).__name__}; use job(...)")
        return NotImplemented


class _Queues:
    """A worker's two queues as it receives them: pickled while it starts, unpickled by the worker
    itself (:meth:`open`). A queue's semaphores are gone once this process has ended (Ctrl-C
    while the forkserver had yet to fork a worker): the worker then ends quietly, where
    multiprocessing's own start-up would print a traceback."""

    def __init__(self, tasks, reports) -> None:
        self.queues = (tasks, reports)

    def __getstate__(self) -> bytes:
        return bytes(ForkingPickler.dumps(self.queues))  # as the worker starts: fds, semaphores

    def __setstate__(self, state: bytes) -> None:
        self.pickled = state

    def open(self) -> tuple | None:
        """(tasks, reports), or None once the process that made them has ended."""
        try:
            return pickle.loads(self.pickled)
        except FileNotFoundError:  # a semaphore that its process unlinked as it ended
            return None


def figure_path(folder: Path, tag: str) -> Path:
    """Where the figure ``tag`` is written in ``folder``."""
    return folder / f"{tag.replace('/', '_')}.png"


def _work(folder: Path, queues: _Queues) -> None:
    """A worker: for each job until ``None``, report ``("start", pid, index, None)``, then
    ``("figure", pid, index, (tag, shape))`` per figure and ``("done", pid, index, None)``, or
    ``("error", pid, index, OSError or traceback)``. Ctrl-C is the parent's to handle: the
    forkserver's children ignore it (:func:`costseg.workers.start`); a worker forked after the
    parent ended ends at once, without a word."""
    if (opened := queues.open()) is None:
        return
    tasks, reports = opened
    import matplotlib

    from costseg.report.files import render, write_png

    pid, index = os.getpid(), -1
    try:
        # A fixed title height: matplotlib's default measures every tick label at each draw to
        # lift the title over ticks at the top, and none of these figures has any.
        with matplotlib.rc_context({"axes.titley": 1.0}):
            while (task := _next_task(tasks)) is not None:
                index, payload = task
                reports.put(("start", pid, index, None))
                for tag, fig in pickle.loads(payload)():
                    image = render(fig)
                    write_png(figure_path(folder, tag), image)
                    reports.put(("figure", pid, index, (tag, image.shape)))
                reports.put(("done", pid, index, None))
    except OSError as err:
        reports.put(("error", pid, index, OSError(err.errno, err.strerror, err.filename)))
    except BaseException:
        reports.put(("error", pid, index, traceback.format_exc()))


def _next_task(tasks):
    """The next task; None once the parent has ended (killed: nobody would send one)."""
    while True:
        try:
            return tasks.get(timeout=1)
        except queue.Empty:
            if not multiprocessing.parent_process().is_alive():
                return None
