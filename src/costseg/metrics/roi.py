"""RoIPrecisionRecall: pixel-wise confusion counts per decision rule and RoI
(docs/definitions.md §4); the core is :mod:`costseg.metrics.functional.roi`."""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor
from torchmetrics import Metric

from costseg.classes import IGNORE_INDEX, NUM_CLASSES, NUM_ROIS
from costseg.metrics.functional.roi import roi_metrics, rule_confusion
from costseg.metrics.shapes import KeepShapes


class RoIPrecisionRecall(KeepShapes, Metric):
    """Confusion matrices of K decision rules over the whole image and each RoI.

    The only state is the int64 (K, R+1, N, N) confusion count (``cm[k, r, t, p]``, r = 0: whole
    image), summed across batches and processes.

    Args:
        num_classes: N.
        num_rules: K, the number of decision rules in each ``preds``.
        num_rois: R.
        ignore_index: target value that counts nowhere.
        kwargs: torchmetrics' options of every ``Metric`` (e.g. ``sync_on_compute``).

    ``compute()`` returns "confmat" (K, R+1, N, N) int64; "precision", "recall" (K, R+1, N)
    float64, NaN for 0/0; "iou" (K, N) float64 over the whole image, NaN for a class absent from
    both target and prediction; "miou" (K,) the mean of iou over the other classes. That is what
    ``torchmetrics``' ``MulticlassJaccardIndex(average="macro", ignore_index=255)`` does (1.9:
    classes whose confusion row and column are both empty get weight 0), so the numbers agree;
    with nothing counted at all, miou is NaN.

    >>> m = RoIPrecisionRecall(num_classes=3, num_rois=1)
    >>> m.update(torch.tensor([[[0, 1], [1, 1]]]), torch.tensor([[[0, 1], [0, 255]]]),
    ...          roi=torch.tensor([[1, 1], [0, 0]]))
    >>> out = m.compute()
    >>> out["recall"][0].tolist()                    # whole image, then RoI 1
    [[0.5, 1.0, nan], [1.0, 1.0, nan]]
    >>> out["iou"][0].tolist(), out["miou"].tolist()
    ([0.5, 0.5, nan], [0.5])
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

    def update(self, preds: Tensor, target: Tensor, roi: Tensor | None = None) -> None:
        """Add a batch: preds (B, K, H, W) (or (B, H, W) when K = 1), target (B, H, W), roi
        None, (H, W) or (B, H, W)."""
        self.confmat += rule_confusion(
            preds, target, roi, self.num_classes, self.num_rules, self.num_rois, self.ignore_index
        )

    def compute(self) -> dict[str, Tensor]:
        """Confusion counts, precision, recall, IoU and mIoU (shapes in the class docstring)."""
        return roi_metrics(self.confmat)
