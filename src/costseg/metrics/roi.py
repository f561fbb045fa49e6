"""RoIPrecisionRecall: pixel-wise confusion counts per decision rule and RoI (SPEC §4)."""

from __future__ import annotations

import functools

import torch
from torch import Tensor

from costseg.classes import IGNORE_INDEX, NUM_CLASSES
from costseg.metrics.base import SumMetric
from costseg.metrics.functional import (
    as_rules,
    iou_from_confusion,
    precision_recall,
    roi_confusion,
)

COMPILED_MIN_RULES = 16  # from this many rules on (sweeps), the CPU counts in one compiled pass;
# fewer do not pay for importing numba (about 0.8 s of an evaluation's start)


@functools.cache
def _compiled_confusion():
    """:func:`costseg.metrics.confusion_counts.count_confusion` where numba imports, else None."""
    try:
        from costseg.metrics.confusion_counts import count_confusion
    except ImportError:
        return None
    return count_confusion


class RoIPrecisionRecall(SumMetric):
    """Confusion matrices of K decision rules over the whole image and each RoI.

    The only state is the int64 (K, R+1, N, N) confusion count (``cm[k, r, t, p]``, r = 0: whole
    image), summed across batches and processes.

    Args:
        num_classes: N.
        num_rules: K, the number of decision rules in each ``preds``.
        num_rois: R.
        ignore_index: target value that counts nowhere.

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

    def __init__(
        self,
        num_classes: int = NUM_CLASSES,
        num_rules: int = 1,
        num_rois: int = 4,
        ignore_index: int = IGNORE_INDEX,
    ) -> None:
        super().__init__()
        if num_classes < 1 or num_rules < 1 or num_rois < 0:
            raise ValueError(
                "expected num_classes >= 1, num_rules >= 1, num_rois >= 0, "
                f"got {num_classes}, {num_rules}, {num_rois}"
            )
        self.num_classes, self.num_rules, self.num_rois = num_classes, num_rules, num_rois
        self.ignore_index = ignore_index
        shape = (num_rules, num_rois + 1, num_classes, num_classes)
        self.add_state("confmat", torch.zeros(shape, dtype=torch.long))

    def update(self, preds: Tensor, target: Tensor, roi: Tensor | None = None) -> None:
        """Add a batch: preds (B, K, H, W) (or (B, H, W) when K = 1), target (B, H, W), roi
        None, (H, W) or (B, H, W)."""
        rules = as_rules(preds, self.num_rules)
        sweep = self.num_rules >= COMPILED_MIN_RULES and rules.device.type == "cpu"
        if sweep and (count := _compiled_confusion()):
            n, r, ignore = self.num_classes, self.num_rois, self.ignore_index
            self.confmat += count(rules, target, roi, n, r, ignore)
            return
        if self.num_rules > 1:
            rules, target, roi = self._count_agreeing_once(rules, target, roi)
        self.confmat += roi_confusion(
            rules, target, roi, self.num_classes, self.num_rois, self.ignore_index
        )

    def _count_agreeing_once(
        self, rules: Tensor, target: Tensor, roi: Tensor | None
    ) -> tuple[Tensor, Tensor, Tensor | None]:
        """Count pixels on which all K rules agree once, for every rule; return the others.

        In a sweep most pixels get the same class from every rule, so this saves most of the
        K-fold counting. The rest come back as one (1, K, 1, P') batch.
        """
        agree = (rules == rules[:, :1]).all(1)  # (B, H, W)
        roi = None if roi is None else roi.expand_as(target)
        shared = roi_confusion(
            rules[:, 0][agree].view(1, 1, -1),
            target[agree].view(1, 1, -1),
            None if roi is None else roi[agree].view(1, 1, -1),
            self.num_classes,
            self.num_rois,
            self.ignore_index,
        )
        self.confmat += shared
        other = ~agree
        rest = rules.transpose(0, 1)[:, other].view(1, self.num_rules, 1, -1)
        rest_roi = None if roi is None else roi[other].view(1, 1, -1)
        return rest, target[other].view(1, 1, -1), rest_roi

    def _compute(self) -> dict[str, Tensor]:
        """Confusion counts, precision, recall, IoU and mIoU (shapes in the class docstring)."""
        precision, recall = precision_recall(self.confmat)
        iou = iou_from_confusion(self.confmat[:, 0])
        return {
            "confmat": self.confmat,
            "precision": precision,
            "recall": recall,
            "iou": iou,
            "miou": iou.nanmean(-1),
        }
