"""Metrics of SPEC §4: pixel-wise precision / recall per RoI and segment-wise errors.

Pure functions live in :mod:`costseg.metrics.functional`; the classes here are thin
``torchmetrics.Metric`` wrappers whose states are count sums.
"""

from costseg.metrics.roi import RoIPrecisionRecall
from costseg.metrics.segments import SegmentErrors

__all__ = ["RoIPrecisionRecall", "SegmentErrors"]
