"""Regional value systems in the decision layer (docs/definitions.md §21): a stack of matrices
and a RoI map that gives each pixel the matrix it is decided with.

What every path shares: the stack's distinct matrices (:func:`distinct`: RoIs with equal
matrices are decided together, and a stack of equal matrices is one plain matrix), and
:func:`by_region`, which makes a single-rule path regional by deciding each distinct matrix's
pixels, gathered. The ``numba`` path decides runs of pixels in place instead
(:func:`costseg.decision.cpu.numba_path.decide_regional`).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch

from costseg.decision.label_maps import empty_labels


def distinct(stack: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The distinct matrices of a (K, M, N) stack, in order of first appearance, and (K,) int64
    the index among them of each matrix of the stack.

    >>> eye = torch.eye(2)
    >>> matrices, index = distinct(torch.stack([eye, 2 * eye, eye]))
    >>> len(matrices), index.tolist()
    (2, [0, 1, 0])
    """
    kept: list[torch.Tensor] = []
    index = []
    for matrix in stack:
        same = next((d for d, m in enumerate(kept) if torch.equal(m, matrix)), None)
        if same is None:
            same = len(kept)
            kept.append(matrix)
        index.append(same)
    return torch.stack(kept), torch.tensor(index)


def matrix_ids(roi: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
    """(B', H·W) uint8 the distinct matrix of each pixel, from (B', H, W) RoI ids and
    :func:`distinct`'s index (at most 256 matrices: a RoI map's ids are uint8 in the graph)."""
    same = torch.equal(index, torch.arange(len(index)))  # every matrix distinct: the ids as given
    if roi.device.type == "cpu":  # numpy: 10 times faster than torch's conversions here
        ids = roi.numpy()
        ids = ids.astype(np.uint8, copy=False) if same else index.numpy().astype(np.uint8)[ids]
        return torch.from_numpy(ids.reshape(len(roi), -1))
    ids = roi.to(torch.uint8) if same else index.to(torch.uint8, roi.device)[roi.long()]
    return ids.reshape(len(roi), -1)


def by_region(decide_one: Callable) -> Callable:
    """A path's single-rule ``decide(probs, cost (1, M, N), priors) → (B, H, W) rows`` made
    regional, ``decide_regional(probs, stack (K, M, N), priors, roi (B' , H, W)) → rows``: each
    distinct matrix decides its pixels, gathered into a (B, N, 1, P) image; every pixel's row is
    the one the path gives it alone, so the path's exactness carries over."""

    def decide_regional(probs: torch.Tensor, stack: torch.Tensor, priors, roi: torch.Tensor):
        matrices, index = distinct(stack)
        b, n, h, w = probs.shape
        ids = matrix_ids(roi, index)
        flat = probs.reshape(b, n, h * w)
        out = empty_labels(b, h * w, dtype=torch.long, device=probs.device)
        for i in range(len(ids)):  # one RoI map for every image, or one per image
            images = slice(None) if len(ids) == 1 else slice(i, i + 1)
            for d in range(len(matrices)):
                pixels = (ids[i] == d).nonzero()[:, 0]
                if not len(pixels):
                    continue
                some = flat[images].index_select(2, pixels)[:, :, None]
                if priors is not None and priors.ndim > 1:
                    priors_d = priors.reshape(n, -1).index_select(1, pixels)[:, None]
                else:
                    priors_d = priors
                rows = decide_one(some, matrices[d : d + 1], priors_d)
                out[images][:, pixels] = rows.reshape(len(some), -1)
        return out.view(b, h, w)

    return decide_regional
