"""Metrics of docs/definitions.md §4, §6 and §9: pixel-wise precision / recall per RoI,
segment-wise errors, instances missed entirely and calibration error, as
:class:`torchmetrics.Metric` s.

Each family is a functional core in :mod:`costseg.metrics.functional` (a batch → sums, sums →
metrics) and a thin Metric here that holds the sums as states (``dist_reduce_fx="sum"``), so the
metrics are the same in one batch, many batches, across DDP processes and in a
:class:`torchmetrics.MetricCollection`. The reported names are listed once in
:mod:`costseg.metrics.names`.
"""

from costseg.metrics.calibration import CalibrationError
from costseg.metrics.instances import InstanceMisses
from costseg.metrics.roi import RoIPrecisionRecall
from costseg.metrics.segments import SegmentErrors

__all__ = ["CalibrationError", "InstanceMisses", "RoIPrecisionRecall", "SegmentErrors"]
