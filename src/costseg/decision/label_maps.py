"""Label maps: the label of a deferred pixel, and memory allocated where page faults cost least.

A rule whose matrix has a defer row (docs/definitions.md §14) returns ``DEFERRED`` where
deferring costs least: the argmin's row N becomes that label (:func:`labels_of`).

A (K, H·W) map of a mixture sweep is large (66 × 1024 × 2048 bytes = 138 MB), and a fresh one
is new memory: on the CPU, filled in 4 KiB pages (~34 000 page faults), it made
``decide_mixtures`` about 18 % slower on the bench's image. numpy advises the kernel to back
large arrays with 2 MiB pages (its default on Linux; ``NUMPY_MADVISE_HUGEPAGE=0`` turns it
off): 66 faults. So CPU maps come from numpy.
"""

from __future__ import annotations

import numpy as np
import torch

from costseg.costs import has_defer_row

DEFERRED = 255
"""The label of a deferred pixel (docs/definitions.md §14)."""

_NUMPY = {torch.uint8: np.uint8, torch.int64: np.int64}


def empty_labels(*shape: int, dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    """``torch.empty(*shape, dtype=dtype, device=device)``; on the CPU, numpy's memory."""
    if torch.device(device).type != "cpu" or dtype not in _NUMPY:
        return torch.empty(*shape, dtype=dtype, device=device)
    return torch.from_numpy(np.empty(shape, _NUMPY[dtype]))


def labels_of(rows: torch.Tensor, matrices: torch.Tensor) -> torch.Tensor:
    """The labels of the argmin's rows of (..., R, N) ``matrices``: with a defer row (R = N + 1),
    its index N becomes ``DEFERRED``, in place; without, ``rows`` as they are."""
    n = matrices.shape[-1]
    return rows.masked_fill_(rows == n, DEFERRED) if has_defer_row(matrices) else rows
