"""Metrics of SPEC §4 and §6: pixel-wise precision / recall per RoI, segment-wise errors and
calibration error.

Pure functions live in :mod:`costseg.metrics.functional` (and
:func:`costseg.metrics.calibration.calibration_bins`); the classes here are thin
stateful wrappers (:class:`costseg.metrics.base.SumMetric`, torchmetrics' pattern without its
import cost) whose states are count sums.
"""

from costseg.metrics.calibration import CalibrationError
from costseg.metrics.roi import RoIPrecisionRecall
from costseg.metrics.segments import SegmentErrors

__all__ = ["CalibrationError", "RoIPrecisionRecall", "SegmentErrors"]
