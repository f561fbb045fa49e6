"""Uncertainty per pixel (``docs/definitions.md §13``): predictive entropy, expected entropy and
mutual information, in nats.

A source that runs the network T times (Monte-Carlo dropout's passes, an ensemble's members)
averages the runs' maps p_t into p̄ and keeps, on the fly, the mean of their entropies
E_t H(p_t), so no run is held after it is added (:class:`RunAverage`). Then
MI = H(p̄) − E_t H(p_t) ≥ 0 (Jensen: entropy is concave), 0 for one run or identical runs.

>>> p = torch.tensor([[[[0.5]], [[0.5]]]])          # (B, N, H, W): a fair coin
>>> q = torch.tensor([[[[1.0]], [[0.0]]]])          # a certain one
>>> runs = RunAverage()
>>> runs.add(q); runs.add(q.flip(1))                # two certain runs that disagree
>>> maps = uncertainty_maps(runs.mean, runs.expected_entropy)
>>> {k: round(float(v), 4) for k, v in maps.items()}
{'entropy': 0.6931, 'expected_entropy': 0.0, 'mutual_information': 0.6931}
>>> round(float(entropy(p)), 4), list(uncertainty_maps(p, None))
(0.6931, ['entropy'])
"""

from __future__ import annotations

import torch
from torch import Tensor

OUTPUT_MAPS = ("entropy", "mutual_information")
"""The maps the outputs hold (:func:`output_maps`; the expected entropy is their difference, up
to the clamp at 0)."""


def entropy(probs: Tensor, dim: int = 1) -> Tensor:
    """H(p) = −Σ_k p_k log p_k over ``dim`` (natural log; 0 log 0 = 0), in the input's dtype.

    >>> float(entropy(torch.tensor([1.0, 0.0]), dim=0))
    0.0
    """
    return 0.0 - torch.special.xlogy(probs, probs).sum(dim)  # 0 - x: +0.0 where certain


class RunAverage:
    """The mean of runs' (B, N, H, W) probability maps and of their entropies, one run at a time.

    The maps are summed in the order they come and divided once by their number (as
    Monte-Carlo dropout always averaged), so one run's mean is that run, bit for bit. With
    ``keep_entropy`` False no entropy is computed (the mean alone, for scores that need no
    uncertainty map) and :attr:`expected_entropy` is None.
    """

    def __init__(self, keep_entropy: bool = True) -> None:
        self.keep_entropy = keep_entropy
        self.total: Tensor | None = None
        self.entropy_total: Tensor | None = None
        self.count = 0
        self.several = False  # more than one run behind the mean

    def add(self, probs: Tensor, expected_entropy: Tensor | None = None) -> None:
        """Add one map; with ``expected_entropy`` the map is itself a mean over runs whose mean
        entropy this is (its runs are pooled with the others, each map weighing the same)."""
        h = None
        if self.keep_entropy:
            h = entropy(probs) if expected_entropy is None else expected_entropy.clone()
        if self.total is None:
            self.total, self.entropy_total = probs.clone(), h
        else:
            self.total += probs
            if h is not None:
                self.entropy_total += h
        self.several |= self.count > 0 or expected_entropy is not None
        self.count += 1

    @property
    def mean(self) -> Tensor:
        """p̄: the maps' mean."""
        if self.total is None:
            raise ValueError("no run added")
        return self.total / self.count

    @property
    def expected_entropy(self) -> Tensor | None:
        """E_t H(p_t) (B, H, W) over every run behind the mean, or None for a single run."""
        if not self.several or self.entropy_total is None:
            return None
        return self.entropy_total / self.count


def uncertainty_maps(probs: Tensor, expected_entropy: Tensor | None) -> dict[str, Tensor]:
    """The uncertainty maps of a (B, N, H, W) (or (N, H, W)) map p̄.

    Args:
        probs: p̄, probabilities over dim -3.
        expected_entropy: E_t H(p_t) of the runs p̄ is the mean of, or None for a single run.

    Returns:
        ``{"entropy": H(p̄)}`` and, with ``expected_entropy``, ``"expected_entropy"`` and
        ``"mutual_information"`` = H(p̄) − E_t H(p_t), clamped at 0 (float rounding can take
        it below by a few ulps of the entropies), each of shape (B, H, W) (or (H, W)).
    """
    h = entropy(probs, dim=-3)
    if expected_entropy is None:
        return {"entropy": h}
    return {
        "entropy": h,
        "expected_entropy": expected_entropy,
        "mutual_information": (h - expected_entropy).clamp_min(0),
    }


def output_maps(probs: Tensor, expected_entropy: Tensor | None) -> dict[str, Tensor]:
    """The :data:`OUTPUT_MAPS` among :func:`uncertainty_maps` (the mutual information with
    several runs only).

    >>> list(output_maps(torch.full((1, 2, 3, 4), 0.5), torch.zeros(1, 3, 4)))
    ['entropy', 'mutual_information']
    """
    maps = uncertainty_maps(probs, expected_entropy)
    return {k: maps[k] for k in OUTPUT_MAPS if k in maps}
