"""An independent float64 reference of the decision rule for the tests of predict.py and the
explorer page (docs/definitions.md §1): plain loops, nothing from the code under test."""

from __future__ import annotations

import torch


def decide_reference(
    probs: torch.Tensor, cost: torch.Tensor | None = None, priors: torch.Tensor | None = None
) -> torch.Tensor:
    """(B, N, H, W) probabilities → (B, H, W) int64 decisions.

    The column-shifted matrix ``C - max_k' C[k', ·]``, ``q = p / π`` in float64, the sum over k
    in ascending order (one rounded product and one rounded sum at a time), argmin with ties to
    the lowest index.
    """
    probs = probs.double()
    n = probs.shape[1]
    cost = 1 - torch.eye(n, dtype=torch.float64) if cost is None else cost.double()
    shifted = cost - cost.max(0, keepdim=True).values
    if priors is not None:
        shape = (1, n, 1, 1) if priors.ndim == 1 else (1, n, *priors.shape[1:])
        probs = probs / priors.double().reshape(shape)
    q = probs
    costs = torch.zeros(probs.shape[0], n, *probs.shape[2:], dtype=torch.float64)
    for k in range(n):
        costs = costs + shifted[:, k].reshape(1, n, 1, 1) * q[:, k : k + 1]
    best = torch.zeros(probs.shape[0], *probs.shape[2:], dtype=torch.long)
    low = costs[:, 0].clone()
    for r in range(1, n):  # strict: ties keep the lower class
        better = costs[:, r] < low
        best[better], low[better] = r, costs[:, r][better]
    return best
