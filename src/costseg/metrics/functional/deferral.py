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

from torch import Tensor


def deferral_metrics(confmat: Tensor, deferred: Tensor) -> dict[str, Tensor]:
    """The metrics of deferral (the module's definitions) of K rules.

    Args:
        confmat: (K, R+1, N, N) counts of the pixels that were not deferred (rows = target).
        deferred: (K, R+1, N) deferred pixels per target class.

    Returns:
        float64 (K, R+1, N) "coverage", "selective_recall", "handled_recall"; float64
        (K, R+1) "deferred_rate".
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
    return {
        "coverage": decided / every,
        "selective_recall": tp / decided,
        "handled_recall": (tp + d) / every,
        "deferred_rate": d.sum(-1) / every.sum(-1),
    }
