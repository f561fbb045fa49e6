"""Pure functions behind the metrics (docs/definitions.md §4, §6), one module per family:
:mod:`.roi` (pixel-wise confusion counts, precision, recall, IoU), :mod:`.segments` (segment-wise
errors; :mod:`.segment_rules` for K rules at once) and :mod:`.calibration` (binned ECE). Each
family has an update (a batch → sums) and a result (sums → metrics); the
:class:`torchmetrics.Metric` of :mod:`costseg.metrics` only holds the sums.

>>> import torch
>>> preds, target = torch.tensor([[[0, 1], [1, 1]]]), torch.tensor([[[0, 1], [0, 255]]])
>>> roi_confusion(preds, target, num_classes=2, num_rois=0)[0].tolist()
[[1, 1], [0, 1]]
"""

from costseg.metrics.functional.calibration import calibration_bins, calibration_error
from costseg.metrics.functional.inputs import as_rules, check_batch
from costseg.metrics.functional.roi import (
    iou_from_confusion,
    mean_iou,
    precision_recall,
    roi_confusion,
    roi_metrics,
    rule_confusion,
)
from costseg.metrics.functional.segment_rules import batch_segment_errors, rule_errors
from costseg.metrics.functional.segments import (
    MaskErrors,
    Segments,
    label_segments,
    mask_segment_errors,
    segment_errors,
)

__all__ = [
    "MaskErrors",
    "Segments",
    "as_rules",
    "batch_segment_errors",
    "calibration_bins",
    "calibration_error",
    "check_batch",
    "iou_from_confusion",
    "label_segments",
    "mask_segment_errors",
    "mean_iou",
    "precision_recall",
    "roi_confusion",
    "roi_metrics",
    "rule_confusion",
    "rule_errors",
    "segment_errors",
]
