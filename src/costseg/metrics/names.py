"""The names of the reported metrics, declared once (docs/definitions.md §4).

Every table, file, TensorBoard tag, ``--target`` / ``--maximize`` and per-image loss takes its
metric names from here. A metric reported per rule, class and RoI is a *rate* (a fraction in
[0, 1], NaN when undefined) or a *count*; a new metric adds its name to these lists.

>>> TARGET_METRICS
('precision', 'recall', 'fp_rate', 'fn_rate')
>>> segment_column("fp"), SEGMENT_RATE_PARTS["fn_rate"]
('fp_segments', ('fn', 'n_gt'))
"""

from __future__ import annotations

PIXEL_RATES: tuple[str, ...] = ("precision", "recall")
"""Per rule, class and RoI, from :class:`~costseg.metrics.RoIPrecisionRecall` (pixels)."""

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

RULE_RATES: tuple[str, ...] = ("miou",)
"""Per rule only (over the whole image and the classes)."""

TARGET_METRICS: tuple[str, ...] = (*PIXEL_RATES, *SEGMENT_RATES)
"""The rates per class and RoI that ``--target``, ``--maximize`` and ``--guarantee`` name."""

RATES: tuple[str, ...] = (*TARGET_METRICS, *RULE_RATES)
"""Every reported fraction in [0, 1] (tables show them in percent)."""


def segment_column(count: str) -> str:
    """The result-row column of a segment count: ``fp`` → ``fp_segments``."""
    return f"{count}_segments"


SEGMENT_COLUMNS: tuple[str, ...] = tuple(segment_column(c) for c in SEGMENT_COUNTS)
ERROR_COLUMNS: tuple[str, ...] = SEGMENT_COLUMNS[:2]
"""``fp_segments``, ``fn_segments``: the segment errors of the summaries."""

ROW_METRICS: tuple[str, ...] = (*PIXEL_RATES, *SEGMENT_COLUMNS, *SEGMENT_RATES, *RULE_RATES)
"""The metric columns of a result row (rule × class × RoI), in file order."""

COUNTS: tuple[str, ...] = SEGMENT_COLUMNS
"""The result-row columns that are counts (whole numbers)."""
