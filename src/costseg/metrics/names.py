"""The names of the reported metrics, declared once (docs/definitions.md §4).

Every table, file, TensorBoard tag, ``--target`` / ``--maximize`` and per-image loss takes its
metric names from here. A metric reported per rule, class and RoI is a *rate* (a fraction in
[0, 1], NaN when undefined) or a *count*; a new metric adds its name to these lists.

>>> TARGET_METRICS[:2], TARGET_METRICS[-1]
(('precision', 'recall'), 'instance_recall')
>>> segment_column("fp"), SEGMENT_RATE_PARTS["fn_rate"]
('fp_segments', ('fn', 'n_gt'))
"""

from __future__ import annotations

from collections.abc import Callable

PIXEL_RATE_PARTS: dict[str, Callable] = {
    "precision": lambda tp, fp, fn: (tp, tp + fp),
    "recall": lambda tp, fp, fn: (tp, tp + fn),
    "dice": lambda tp, fp, fn: (2 * tp, 2 * tp + fp + fn),  # F1: precision and recall's mean
}
"""Each pixel rate per rule, class and RoI as (numerator, denominator) of the class's true
positives, false positives and false negatives (a deferred pixel is a false negative of its
class; docs/definitions.md §4, §14). One entry is a new rate everywhere: the metrics
(:func:`~costseg.metrics.functional.roi.pixel_rates`, the per-image losses), result rows,
CSV / JSON, table.md, TensorBoard in training and evaluation, sweep figures and ``--target``."""

PIXEL_RATES: tuple[str, ...] = tuple(PIXEL_RATE_PARTS)
"""Per rule, class and RoI, from :class:`~costseg.metrics.RoIPrecisionRecall` (pixels)."""

PAPER_RATES: tuple[str, ...] = ("precision", "recall")
"""The two pixel rates of the paper's table (docs/definitions.md §5)."""

DEFER_RATE_PARTS: dict[str, Callable] = {
    "coverage": lambda tp, decided, deferred: (decided, decided + deferred),
    "selective_recall": lambda tp, decided, deferred: (tp, decided),
    "handled_recall": lambda tp, decided, deferred: (tp + deferred, decided + deferred),
}
"""Each rate of deferral per rule, class and RoI as (numerator, denominator) of the class's
true positives, its pixels that were decided and those deferred (docs/definitions.md §14;
:mod:`costseg.metrics.functional.deferral`, the per-image losses)."""

DEFER_RATES: tuple[str, ...] = tuple(DEFER_RATE_PARTS)
"""Per rule, class and RoI, from :class:`~costseg.metrics.RoIPrecisionRecall`: what deferring
did."""

DEFER_RULE_RATES: tuple[str, ...] = ("deferred_rate",)
"""Per rule and RoI: the share of the RoI's valid pixels that were deferred."""

RISK_COVERAGE_RATES: tuple[str, ...] = (
    "selective_error",
    "coverage_all_classes",
    "selective_error_all_classes",
)
"""The columns a defer sweep's rows add (docs/definitions.md §14): per class and RoI the
selective error ``1 − selective_recall``; per rule and RoI over all classes the coverage
``1 − deferred_rate`` and the selective error ``1 − selective pixel accuracy``."""

DEFER_COLUMNS: tuple[str, ...] = (*DEFER_RATES, *DEFER_RULE_RATES)
"""The metric columns of a result row that only groups with a deferring rule have."""

SEGMENT_COUNTS: tuple[str, ...] = ("fp", "fn", "n_pred", "n_gt")
"""Per rule, class and RoI, from :class:`~costseg.metrics.SegmentErrors`: false-positive and
false-negative segments, predicted and ground-truth segments (also the order of the rows of
:func:`~costseg.metrics.functional.mask_segment_errors`' counts)."""

SEGMENT_RATE_PARTS: dict[str, tuple[str, str]] = {
    "fp_rate": ("fp", "n_pred"),
    "fn_rate": ("fn", "n_gt"),
}
"""Each segment rate as (numerator, denominator) among :data:`SEGMENT_COUNTS`."""

SEGMENT_RATES: tuple[str, ...] = tuple(SEGMENT_RATE_PARTS)

INSTANCE_RATES: tuple[str, ...] = ("instance_recall",)
"""Per rule, class and RoI, from :class:`~costseg.metrics.InstanceMisses` (docs/definitions.md
§9): the fraction of ground-truth instances with at least one pixel predicted as their class."""

INSTANCE_COUNTS: tuple[str, ...] = (
    "gt_instances",
    "missed_instances",
    "missed_small",
    "missed_medium",
    "missed_large",
)
"""Ground-truth instances, those missed entirely, and the missed ones by area."""

INSTANCE_COLUMNS: tuple[str, ...] = (*INSTANCE_COUNTS[:2], *INSTANCE_RATES, *INSTANCE_COUNTS[2:])
"""The instance columns of a result row, where instances are measured."""

RULE_RATES: tuple[str, ...] = ("miou",)
"""Per rule only (over the whole image and the classes)."""

TARGET_METRICS: tuple[str, ...] = (*PIXEL_RATES, *DEFER_RATES, *SEGMENT_RATES, *INSTANCE_RATES)
"""The rates per class and RoI that ``--target``, ``--maximize`` and ``--guarantee`` name."""

HIGHER_IS_BETTER: tuple[str, ...] = (*PIXEL_RATES, *DEFER_RATES, *INSTANCE_RATES)
"""The target metrics where higher is better: a per-image loss or a guarantee takes 1 − the
metric (the segment rates are losses themselves)."""

RATES: tuple[str, ...] = (*TARGET_METRICS, *DEFER_RULE_RATES, *RISK_COVERAGE_RATES, *RULE_RATES)
"""Every reported fraction in [0, 1] (tables show them in percent)."""


def segment_column(count: str) -> str:
    """The result-row column of a segment count: ``fp`` → ``fp_segments``."""
    return f"{count}_segments"


SEGMENT_COLUMNS: tuple[str, ...] = tuple(segment_column(c) for c in SEGMENT_COUNTS)
ERROR_COLUMNS: tuple[str, ...] = SEGMENT_COLUMNS[:2]
"""``fp_segments``, ``fn_segments``: the segment errors of the summaries."""

ROW_METRICS: tuple[str, ...] = (
    *PIXEL_RATES,
    *DEFER_COLUMNS,
    *SEGMENT_COLUMNS,
    *SEGMENT_RATES,
    *INSTANCE_COLUMNS,
    *RULE_RATES,
)
"""The metric columns of a result row (rule × class × RoI), in file order (the defer columns
only where a rule of the group defers)."""

COUNTS: tuple[str, ...] = (*SEGMENT_COLUMNS, *INSTANCE_COUNTS)
"""The result-row columns that are counts (whole numbers)."""
