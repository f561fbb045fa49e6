"""Label maps allocated where page faults cost least.

A (K, H·W) map of a mixture sweep is large (66 × 1024 × 2048 bytes = 138 MB), and a fresh one
is new memory: on the CPU, filled in 4 KiB pages (~34 000 page faults), it made
``decide_mixtures`` about 18 % slower on the bench's image. numpy advises the kernel to back
large arrays with 2 MiB pages (its default on Linux; ``NUMPY_MADVISE_HUGEPAGE=0`` turns it
off): 66 faults. So CPU maps come from numpy.
"""

from __future__ import annotations

import numpy as np
import torch

_NUMPY = {torch.uint8: np.uint8, torch.int64: np.int64}


def empty_labels(*shape: int, dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    """``torch.empty(*shape, dtype=dtype, device=device)``; on the CPU, numpy's memory."""
    if torch.device(device).type != "cpu" or dtype not in _NUMPY:
        return torch.empty(*shape, dtype=dtype, device=device)
    return torch.from_numpy(np.empty(shape, _NUMPY[dtype]))
