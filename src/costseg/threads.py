"""The one thread pool of the compiled and C-level passes (numba kernels, scipy's labelling,
numpy's unpacking), which run without the GIL for the most part, and how work is cut for it."""

from __future__ import annotations

import functools
import os
from concurrent.futures import ThreadPoolExecutor


@functools.cache
def threads() -> ThreadPoolExecutor:
    return ThreadPoolExecutor(len(os.sched_getaffinity(0)), thread_name_prefix="costseg")


os.register_at_fork(after_in_child=threads.cache_clear)  # a forked child has none of its threads


def in_pieces(kernel, args: tuple, count: int, align: int = 1, per_thread: int = 4) -> list:
    """``kernel(*args, start, stop)`` over ``range(count)`` in ``per_thread`` pieces per thread
    (taken in turn by the threads that are free), each starting at a multiple of ``align``;
    their results in order."""
    step = max(1, -(-count // (per_thread * threads()._max_workers)))
    step = -(-step // align) * align
    pieces = [(s, min(s + step, count)) for s in range(0, count, step)]
    return [job.result() for job in [threads().submit(kernel, *args, *p) for p in pieces]]
