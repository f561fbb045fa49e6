"""The one way costseg starts worker processes: multiprocessing's forkserver.

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

import multiprocessing

PRELOAD = [
    "costseg.report.drawing",
    "costseg.report.figures",
    "costseg.report.ternary",
    "costseg.report.cost_matrix",
    "costseg.report.curves",
    "costseg.report.priors",
    "costseg.report.uncertainty",
    "costseg.data.toy",
    "costseg.data.cityscapes",
]
"""Modules the forkserver imports once, so that a worker forked from it starts at once."""

STALL_SECONDS = 600.0
"""How long a wait on a worker may pass without a figure drawn or a batch loaded. One figure of
a 1024 × 2048 evaluation takes seconds (docs/speed.md); ten minutes without one is a stall."""

CONTEXT = multiprocessing.get_context("forkserver")
CONTEXT.set_forkserver_preload(PRELOAD)


def start() -> None:
    """Start the forkserver now (it imports :data:`PRELOAD` while this process goes on), so
    that the first worker does not wait for it. Returns at once; later calls do nothing."""
    from multiprocessing import forkserver

    forkserver.ensure_running()


class Stalled(RuntimeError):
    """A worker process or thread stopped making progress, or ended before its work was done.
    The command line ends with its message, one line (``costseg.cli.user_errors``)."""
