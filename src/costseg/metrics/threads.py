"""The thread pool of the metrics' compiled and C-level work (numba kernels, scipy's labelling,
numpy's unpacking), which runs without the GIL for the most part."""

from __future__ import annotations

import functools
import os
from concurrent.futures import ThreadPoolExecutor


@functools.cache
def threads() -> ThreadPoolExecutor:
    return ThreadPoolExecutor(len(os.sched_getaffinity(0)), thread_name_prefix="metrics")


os.register_at_fork(after_in_child=threads.cache_clear)  # a forked child has none of its threads
