"""Where costseg's work runs beside the main thread, and how long it is waited for.

**Threads.** The one thread pool of the compiled and C-level passes (numba kernels, scipy's
labelling, numpy's unpacking), which run without the GIL for the most part, and how work is cut
for it (:func:`threads`, :func:`in_pieces`).

**Processes.** Every worker process comes from multiprocessing's forkserver (:data:`CONTEXT`).
``fork`` copies a process's memory but not its threads. Once torch has run an operation (its
intra-op thread pool), or any thread of ours or of TensorBoard is alive, a forked child can hold
a copy of a lock that a thread held at that moment and that nobody will ever release; the child
then waits forever at its first torch call or allocation behind that lock. The forkserver is a
fresh interpreter (started with fork + exec, which copies no lock) that imports :data:`PRELOAD`
and then does nothing but fork on request: it never runs torch or starts a thread of its own
(NumPy's BLAS threads stop before each fork, by OpenBLAS's own fork handler), so every worker
forked from it starts from a process in which no lock can be held.

Figure workers (:mod:`costseg.report.drawing`) and DataLoader workers (``multiprocessing_context``)
all come from :data:`CONTEXT`. :data:`STALL_SECONDS` bounds every wait on such a worker: one
figure or one batch that takes longer means a stalled worker, never a healthy one.
"""

from __future__ import annotations

import bisect
import contextlib
import functools
import itertools
import multiprocessing
import os
import signal
import threading
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor
from typing import TypeVar

T = TypeVar("T")

PRELOAD = [
    "costseg.report.drawing",
    "matplotlib.figure",
    "matplotlib.backends.backend_agg",
    "costseg.data.toy",
]
"""Modules the forkserver imports once, so that a worker forked from it starts at once: the
drawing workers' loop and what every figure needs, and the procedural scenes' (a Cityscapes
loader's workers import torchvision themselves, 1.3 s, rather than every evaluation's
forkserver). A job adds the modules of the
figures it will draw (:func:`start`: an evaluation's analyses declare theirs)."""

STALL_SECONDS = 600.0
"""How long a wait on a worker may pass without a figure drawn or a batch loaded. One figure of
a 1024 × 2048 evaluation takes seconds; ten minutes without one is a stall."""

CONTEXT = multiprocessing.get_context("forkserver")
CONTEXT.set_forkserver_preload(PRELOAD)
_started = False  # whether start() ran: the forkserver's preloads are then fixed


def start(preload: Sequence[str] = ()) -> None:
    """Start the forkserver now (it imports :data:`PRELOAD` and ``preload``, the modules of the
    figures this job will draw, while this process goes on), so that the first worker does not
    wait for it. Returns at once; later calls do nothing.

    It starts with Ctrl-C ignored, as do the workers it forks: Ctrl-C is this process's to
    handle (it stops the workers), and a worker or the forkserver itself must not print a
    traceback of its own."""
    from multiprocessing import forkserver

    global _started
    if preload and not _started:  # the forkserver imports its preloads as it starts, once
        CONTEXT.set_forkserver_preload([*PRELOAD, *preload])
    _started = True
    if threading.current_thread() is not threading.main_thread():
        forkserver.ensure_running()  # only the main thread may set signal handlers
        return
    handler = signal.signal(signal.SIGINT, signal.SIG_IGN)  # inherited through exec
    try:
        forkserver.ensure_running()
    finally:
        signal.signal(signal.SIGINT, handler)


class Stalled(RuntimeError):
    """A worker process or thread stopped making progress, or ended before its work was done.
    The command line ends with its message, one line (``costseg.cli.user_errors``)."""


def loader_options(num_workers: int) -> dict:
    """A DataLoader's keywords for ``num_workers`` workers, at most one per usable CPU (more
    only compete for them, and torch warns): forked from the forkserver, and a batch that does
    not come within :data:`STALL_SECONDS` is an error, not a wait.

    >>> loader_options(0)
    {'num_workers': 0}
    """
    if num_workers == 0:
        return {"num_workers": 0}
    start()
    return {
        "num_workers": min(num_workers, len(os.sched_getaffinity(0))),
        "multiprocessing_context": CONTEXT,
        "timeout": STALL_SECONDS,
    }


@contextlib.contextmanager
def loader_errors(what: str) -> Iterator[None]:
    """Turn a DataLoader's errors about its workers (no batch within its timeout, a worker that
    died) into :class:`Stalled` naming ``what`` was being loaded."""
    try:
        yield
    except RuntimeError as err:
        if not str(err).startswith(("DataLoader timed out", "DataLoader worker")):
            raise
        raise Stalled(f"{err} while loading {what}") from err


def within(call: Callable[[], T], what: str) -> T:
    """``call()`` on a thread of its own, waited for at most :data:`STALL_SECONDS`: its result,
    its exception raised here, or :class:`Stalled` naming ``what`` (the thread, a daemon, is
    left behind: it cannot hold up the exit).

    >>> within(lambda: 2 + 2, "a sum")
    4
    """
    outcome: dict = {}

    def run() -> None:
        try:
            outcome["value"] = call()
        except BaseException as err:  # raised in the caller's thread
            outcome["error"] = err

    thread = threading.Thread(target=run, name=what, daemon=True)
    thread.start()
    thread.join(STALL_SECONDS)
    if thread.is_alive():
        raise Stalled(f"{what} did not finish within {STALL_SECONDS:.0f} s")
    if "error" in outcome:
        raise outcome["error"]
    return outcome["value"]


@functools.cache
def threads() -> ThreadPoolExecutor:
    return ThreadPoolExecutor(len(os.sched_getaffinity(0)), thread_name_prefix="costseg")


def in_pieces(
    kernel, args: tuple, count: int, align: int = 1, per_thread: int = 4, work=None
) -> list:
    """``kernel(*args, start, stop)`` over ``range(count)`` in ``per_thread`` pieces per thread
    (taken in turn by the threads that are free), each starting at a multiple of ``align``;
    their results in order. ``work``: (count,) the work of each item (e.g. a run's pixels), for
    pieces of about equal work instead of equal counts."""
    total = per_thread * threads()._max_workers
    if work is not None and count:  # cut where the work so far passes each share of the total
        done = list(itertools.accumulate(int(w) for w in work))
        cuts = {bisect.bisect_left(done, done[-1] * k / total) + 1 for k in range(1, total)}
        pieces = list(itertools.pairwise(sorted({0, count} | {c for c in cuts if c < count})))
    else:
        step = max(1, -(-count // total))
        step = -(-step // align) * align
        pieces = [(s, min(s + step, count)) for s in range(0, count, step)]
    return [job.result() for job in [threads().submit(kernel, *args, *p) for p in pieces]]
