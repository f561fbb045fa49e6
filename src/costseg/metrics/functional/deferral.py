"""What deferring did (docs/definitions.md §14), from the counts of
:class:`~costseg.metrics.RoIPrecisionRecall`: the confusion counts of the pixels that were not
deferred and, per target class, the pixels that were.

Per rule, RoI and class c, with ``TP`` the pixels of c predicted c, ``G`` every valid pixel of
c and ``D`` those of them deferred:

* ``coverage = (G − D) / G``: the share of c's pixels not deferred;
* ``selective_recall = TP / (G − D)``: recall over the pixels not deferred;
* ``handled_recall = (TP + D) / G``: predicted c or deferred (a deferred pedestrian is seen
  as uncertain, not missed);
* per rule and RoI, ``deferred_rate``: the share of all valid pixels that were deferred.

Selective precision is precision itself: a deferred pixel is predicted as no class, so the
pixels predicted c are the same with or without the deferred ones. 0/0 is NaN.

Risk–coverage (a sweep of the defer cost): per class, coverage against the selective error
``1 − selective_recall``; over all classes of a RoI, ``1 − deferred_rate`` against
:func:`selective_error`; :func:`risk_coverage_area` is the area under such a curve (AURC).

>>> import torch
>>> cm = torch.tensor([[[[3, 1], [0, 2]]]])          # (K=1, R+1=1, N=2, N): not deferred
>>> deferred = torch.tensor([[[4, 0]]])               # four pixels of class 0 deferred
>>> out = deferral_metrics(cm, deferred)
>>> out["coverage"].tolist(), out["selective_recall"].tolist(), out["handled_recall"].tolist()
([[[0.5, 1.0]]], [[[0.75, 1.0]]], [[[0.875, 1.0]]])
>>> out["deferred_rate"].tolist()
[[0.4]]
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence

from torch import Tensor

from costseg.metrics.names import DEFER_RATE_PARTS


def deferral_metrics(confmat: Tensor, deferred: Tensor) -> dict[str, Tensor]:
    """The metrics of deferral (the module's definitions) of K rules.

    Args:
        confmat: (K, R+1, N, N) counts of the pixels that were not deferred (rows = target).
        deferred: (K, R+1, N) deferred pixels per target class.

    Returns:
        float64 (K, R+1, N) "coverage", "selective_recall", "handled_recall"; float64
        (K, R+1) "deferred_rate" and "coverage_all_classes" (1 − "deferred_rate").
    """
    if deferred.shape != confmat.shape[:-1]:
        raise ValueError(
            f"expected deferred counts of shape {tuple(confmat.shape[:-1])}, "
            f"got {tuple(deferred.shape)}"
        )
    cm, d = confmat.double(), deferred.double()
    tp = cm.diagonal(dim1=-2, dim2=-1)
    decided = cm.sum(-1)  # pixels of each class that were not deferred
    every = decided + d
    rates = {name: parts(tp, decided, d) for name, parts in DEFER_RATE_PARTS.items()}
    return {
        **{name: numerator / denominator for name, (numerator, denominator) in rates.items()},
        "deferred_rate": d.sum(-1) / every.sum(-1),
        "coverage_all_classes": decided.sum(-1) / every.sum(-1),
    }


def selective_error(confmat: Tensor) -> Tensor:
    """1 − selective pixel accuracy over all classes: the share of the pixels that were not
    deferred whose predicted class is wrong; NaN where nothing is left.

    Args:
        confmat: (..., N, N) counts of the pixels that were not deferred (rows = target).

    Returns:
        float64 (...,), e.g. (K, R+1) per rule and RoI.

    >>> import torch
    >>> selective_error(torch.tensor([[3, 1], [0, 4]])).item()
    0.125
    """
    cm = confmat.double()
    return 1 - cm.diagonal(dim1=-2, dim2=-1).sum(-1) / cm.sum((-2, -1))


def risk_coverage_area(coverage: Sequence[float], risk: Sequence[float]) -> float:
    """AURC: the area under the risk–coverage curve by trapezoids over coverage.

    The points are sorted by coverage; a point whose coverage or risk is NaN (no pixel of the
    class, or none left undeferred) is left out. The area spans only the coverages the points
    reach, from the smallest to the largest (nothing is extrapolated to coverage 0 or 1); NaN
    with fewer than two points.

    >>> risk_coverage_area([1.0, 0.5, 0.0], [0.25, 0.125, float("nan")])   # one trapezoid
    0.09375
    """
    points = sorted(
        (float(c), float(r))
        for c, r in zip(coverage, risk, strict=True)
        if not (math.isnan(c) or math.isnan(r))
    )
    if len(points) < 2:
        return math.nan
    return sum((c1 - c0) * (r0 + r1) / 2 for (c0, r0), (c1, r1) in itertools.pairwise(points))
