"""RoIPrecisionRecall: pixel-wise confusion counts per decision rule and RoI, and the deferred
pixels (docs/definitions.md §4, §14); the core is :mod:`costseg.metrics.functional.roi`."""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor
from torchmetrics import Metric

from costseg.classes import IGNORE_INDEX, NUM_CLASSES, NUM_ROIS
from costseg.decision.label_maps import DEFERRED
from costseg.metrics.functional.roi import roi_metrics, rule_confusion
from costseg.metrics.shapes import KeepShapes


class RoIPrecisionRecall(KeepShapes, Metric):
    """Confusion matrices of K decision rules over the whole image and each RoI.

    The states are the int64 (K, R+1, N, N) confusion count of the pixels that were not deferred
    (``cm[k, r, t, p]``, r = 0: whole image) and the int64 (K, R+1, N) count of the pixels of
    each target class t that were deferred (predictions labelled
    :data:`~costseg.decision.label_maps.DEFERRED`, docs/definitions.md §14; for N <= 255),
    summed across batches and processes. Without deferred pixels the second stays 0 and every
    other result is what it is without it.

    Args:
        num_classes: N.
        num_rules: K, the number of decision rules in each ``preds``.
        num_rois: R.
        ignore_index: target value that counts nowhere.
        kwargs: torchmetrics' options of every ``Metric`` (e.g. ``sync_on_compute``).

    ``compute()`` returns "confmat" (K, R+1, N, N) and "deferred" (K, R+1, N) int64;
    "precision", "recall" (K, R+1, N) float64, NaN for 0/0; "iou" (K, N) float64 over the whole
    image, NaN for a class absent from both target and prediction; "miou" (K,) the mean of iou
    over the other classes. That is what ``torchmetrics``' ``MulticlassJaccardIndex(
    average="macro", ignore_index=255)`` does (1.9: classes whose confusion row and column are
    both empty get weight 0), so the numbers agree; with nothing counted at all, miou is NaN. A
    deferred pixel is a false negative of its target class in recall and IoU. Also the metrics
    of deferral: "coverage", "selective_recall", "handled_recall" (K, R+1, N) and
    "deferred_rate" (K, R+1) (:mod:`costseg.metrics.functional.deferral`).

    >>> m = RoIPrecisionRecall(num_classes=3, num_rois=1)
    >>> m.update(torch.tensor([[[0, 1], [1, 1]]]), torch.tensor([[[0, 1], [0, 255]]]),
    ...          roi=torch.tensor([[1, 1], [0, 0]]))
    >>> out = m.compute()
    >>> out["recall"][0].tolist()                    # whole image, then RoI 1
    [[0.5, 1.0, nan], [1.0, 1.0, nan]]
    >>> out["iou"][0].tolist(), out["miou"].tolist()
    ([0.5, 0.5, nan], [0.5])
    >>> m.update(torch.tensor([[[255, 1]]]), torch.tensor([[[0, 1]]]))     # 255: deferred
    >>> out = m.compute()
    >>> out["deferred"][0, 0].tolist(), out["recall"][0, 0].tolist()
    ([1, 0, 0], [0.3333333333333333, 1.0, nan])
    >>> out["coverage"][0, 0].tolist(), out["handled_recall"][0, 0].tolist()
    ([0.6666666666666666, 1.0, nan], [0.6666666666666666, 1.0, nan])
    """

    is_differentiable = False
    higher_is_better = True
    full_state_update = False

    def __init__(
        self,
        num_classes: int = NUM_CLASSES,
        num_rules: int = 1,
        num_rois: int = NUM_ROIS,
        ignore_index: int = IGNORE_INDEX,
        **kwargs: Any,
    ) -> None:
        super().__init__(**kwargs)
        if num_classes < 1 or num_rules < 1 or num_rois < 0:
            raise ValueError(
                "expected num_classes >= 1, num_rules >= 1, num_rois >= 0, "
                f"got {num_classes}, {num_rules}, {num_rois}"
            )
        self.num_classes, self.num_rules, self.num_rois = num_classes, num_rules, num_rois
        self.ignore_index = ignore_index
        shape = (num_rules, num_rois + 1, num_classes, num_classes)
        self.add_state("confmat", torch.zeros(shape, dtype=torch.long), dist_reduce_fx="sum")
        self.add_state("deferred", torch.zeros(shape[:-1], dtype=torch.long), dist_reduce_fx="sum")

    def update(self, preds: Tensor, target: Tensor, roi: Tensor | None = None) -> None:
        """Add a batch: preds (B, K, H, W) (or (B, H, W) when K = 1; class ids, or
        ``DEFERRED``), target (B, H, W), roi None, (H, W) or (B, H, W)."""
        n = self.num_classes
        deferred = DEFERRED if n <= DEFERRED else None  # more classes: 255 is one of them
        counts = rule_confusion(
            preds, target, roi, n, self.num_rules, self.num_rois, self.ignore_index, deferred
        )
        self.confmat += counts[..., :n]
        if deferred is not None:
            self.deferred += counts[..., n]

    def compute(self) -> dict[str, Tensor]:
        """Counts, precision, recall, IoU, mIoU and deferral (shapes in the class docstring)."""
        return roi_metrics(self.confmat, self.deferred)
