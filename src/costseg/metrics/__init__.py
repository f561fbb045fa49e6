"""Metrics of docs/definitions.md §4, §6 and §9: pixel-wise precision / recall per RoI,
segment-wise errors, instances missed entirely and calibration error, as
:class:`torchmetrics.Metric` s.

Each family is a functional core in :mod:`costseg.metrics.functional` (a batch → sums, sums →
metrics) and a thin Metric here that holds the sums as states (``dist_reduce_fx="sum"``), so the
metrics are the same in one batch, many batches, across DDP processes and in a
:class:`torchmetrics.MetricCollection`. The reported names are listed once in
:mod:`costseg.metrics.names`.
"""

import importlib

__all__ = ["CalibrationError", "InstanceMisses", "RoIPrecisionRecall", "SegmentErrors"]

_MODULES = {
    "CalibrationError": "calibration",
    "InstanceMisses": "instances",
    "RoIPrecisionRecall": "roi",
    "SegmentErrors": "segments",
}


def __getattr__(name: str):
    """The Metric classes, imported on first use: torchmetrics is slow to import, and the option
    checks read only :mod:`costseg.metrics.names` and :mod:`costseg.metrics.selection`."""
    if name not in _MODULES:
        raise AttributeError(f"module 'costseg.metrics' has no attribute {name!r}")
    return getattr(importlib.import_module(f"costseg.metrics.{_MODULES[name]}"), name)
