"""Result tables as text: GitHub Markdown, the paper's layout, and aligned console output.

Rows are plain dicts, e.g. ``{"matrix": "altruistic", "class": "person", "roi": 1,
"precision": 0.4112, "recall": 0.9981}``. Rates (precision, recall, mIoU, …:
:data:`costseg.metrics.names.RATES`) are fractions and are shown as percentages with two
decimals, like the paper. An undefined ratio (NaN) is shown as ``nan``;
a value that was not measured at all as ``—``.
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Mapping, Sequence
from typing import Any

from costseg.classes import CLASS_NAMES, NUM_CLASSES, NUM_ROIS, ROI_NAMES
from costseg.metrics.names import (
    DEFER_COLUMNS,
    INSTANCE_COLUMNS,
    PAPER_RATES,
    PIXEL_RATES,
    RATES,
    RULE_RATES,
    SEGMENT_COLUMNS,
)
from costseg.rules import DEFER_COLUMN

Row = Mapping[str, Any]

PERCENT = RATES
EXTRA_RATES = tuple(m for m in PIXEL_RATES if m not in PAPER_RATES)
EXTRA_COLUMNS = (
    *EXTRA_RATES,
    *DEFER_COLUMNS,
    *SEGMENT_COLUMNS,
    *INSTANCE_COLUMNS[:3],
    *RULE_RATES,
)
"""Columns added to the paper's layout when the rows have them (and ``defer``, the rule's defer
cost, after ``matrix``)."""

PAPER_TABLE: tuple[dict[str, Any], ...] = tuple(
    {"matrix": m, "class": c, "roi": r, "precision": p, "recall": q}
    for m, c, r, p, q in [
        ("altruistic", "person", 1, 41.12, 99.81),
        ("robotistic", "person", 1, 89.87, 94.98),
        ("egoistic", "person", 1, 93.88, 70.07),
        ("altruistic", "person", 2, 39.42, 99.86),
        ("robotistic", "person", 2, 88.36, 93.93),
        ("egoistic", "person", 2, 95.07, 54.81),
        ("altruistic", "building", 1, 22.56, 93.65),
        ("robotistic", "building", 1, 80.99, 94.94),
        ("egoistic", "building", 1, 15.15, 99.93),
        ("altruistic", "building", 2, 24.94, 95.22),
        ("robotistic", "building", 2, 87.76, 94.58),
        ("egoistic", "building", 2, 18.48, 99.90),
    ]
)
"""The paper's headline table (docs/definitions.md §5): Cityscapes val, DeepLabv3+ Xception;
precision and recall in percent as printed there."""

PAPER_ROIS: tuple[int, ...] = tuple(dict.fromkeys(r["roi"] for r in PAPER_TABLE))
"""The RoIs of the paper's table (1 street, 2 sidewalk): the headline rows."""
PAPER_COLUMNS = ("matrix", "class", "roi", *PAPER_RATES)
"""The columns every row of a paper-style table needs."""

MISSING = "—"


def format_value(value: Any, percent: bool = False) -> str:
    """One table cell: NaN → ``nan``, ``None`` → ``—``, fractions as percentages if ``percent``.

    >>> format_value(0.4112, percent=True), format_value(float("nan"), percent=True)
    ('41.12', 'nan')
    >>> format_value(7), format_value(0.123456), format_value(None), format_value("egoistic")
    ('7', '0.1235', '—', 'egoistic')
    """
    if hasattr(value, "item"):  # numpy / torch scalars
        value = value.item()
    if value is None:
        return MISSING
    if isinstance(value, bool | str) or not isinstance(value, numbers.Real):
        return str(value)
    if isinstance(value, numbers.Integral) and not percent:
        return str(value)
    if math.isnan(value):
        return "nan"
    return f"{100 * value:.2f}" if percent else f"{value:.4g}"


def _cells(rows: Sequence[Row], columns: Sequence[str], percent: Sequence[str]) -> list[list[str]]:
    return [[format_value(row.get(c), c in percent) for c in columns] for row in rows]


def _check_headers(columns: Sequence[str], headers: Sequence[str] | None) -> list[str]:
    if headers is None:
        return list(columns)
    if len(headers) != len(columns):
        raise ValueError(f"expected {len(columns)} headers (one per column), got {len(headers)}")
    return list(headers)


def markdown_table(
    rows: Sequence[Row],
    columns: Sequence[str] | None = None,
    headers: Sequence[str] | None = None,
    percent: Sequence[str] = PERCENT,
) -> str:
    """GitHub Markdown table of ``rows`` restricted to ``columns`` (None: every key of the rows,
    in order; missing keys shown as ``—``).

    >>> print(markdown_table([{"matrix": "ml", "recall": 0.5}], ["matrix", "recall"]))
    | matrix | recall |
    |---|---|
    | ml | 50.00 |
    """
    columns = list(dict.fromkeys(k for r in rows for k in r)) if columns is None else columns
    head = _check_headers(columns, headers)
    lines = [_md_line(head), "|" + "---|" * len(head)]
    lines += [_md_line(cells) for cells in _cells(rows, columns, percent)]
    return "\n".join(lines)


def _md_line(cells: Sequence[str]) -> str:
    return "| " + " | ".join(c.replace("|", "\\|") for c in cells) + " |"


def console_table(
    rows: Sequence[Row],
    columns: Sequence[str],
    headers: Sequence[str] | None = None,
    percent: Sequence[str] = PERCENT,
) -> str:
    """Aligned plain text for a terminal: text left-aligned, numbers right-aligned.

    >>> print(console_table([{"m": "ml", "recall": 0.5}, {"m": "egoistic", "recall": 1.0}],
    ...                     ["m", "recall"]))
    m         recall
    --------  ------
    ml         50.00
    egoistic  100.00
    """
    head = _check_headers(columns, headers)
    body = _cells(rows, columns, percent)
    widths = [max(len(s) for s in col) for col in zip(head, *body, strict=True)]
    numeric = [all(_is_number(r[i]) for r in body) and bool(body) for i in range(len(head))]

    def line(cells: Sequence[str]) -> str:
        aligned = zip(cells, widths, numeric, strict=True)
        parts = [c.rjust(w) if n else c.ljust(w) for c, w, n in aligned]
        return "  ".join(parts).rstrip()

    return "\n".join([line(head), line(["-" * w for w in widths]), *map(line, body)])


def _is_number(cell: str) -> bool:
    try:
        float(cell)
    except ValueError:
        return cell == MISSING
    return True


def _roi_id(roi: Any) -> int:
    return ROI_NAMES.index(roi) if isinstance(roi, str) else int(roi)


def _class_name(cls: Any) -> str:
    return cls if isinstance(cls, str) else CLASS_NAMES[int(cls)]


def _key(row: Row) -> tuple[str, str, int]:
    return str(row["matrix"]).lower(), _class_name(row["class"]), _roi_id(row["roi"])


def _roi_label(roi: Any) -> str:
    roi_id = _roi_id(roi)
    return f"{roi_id} {ROI_NAMES[roi_id]}"


_PAPER = {_key(r): r for r in PAPER_TABLE}
_PAPER_RATES = tuple(f"paper {m}" for m in PAPER_RATES)
_PERCENT_WITH_PAPER = (*PERCENT, *_PAPER_RATES)


def _paper_fractions(paper: Row) -> dict[str, float | None]:
    # The paper prints percent; as fractions they share the measured columns' formatting.
    return {f"paper {k}": paper[k] / 100 if k in paper else None for k in PAPER_RATES}


def paper_table(rows: Sequence[Row]) -> str:
    """Markdown table in the paper's layout: class-major, then RoI, then matrix.

    Classes, RoIs and matrices keep the order in which they first appear in ``rows``; as in the
    paper, a class or RoI is printed only on the first line of its group. Extra columns (defer
    cost and deferral, segment counts, mIoU) are added when any row has them, and the paper's
    own numbers where it has them.
    ``class`` may be a name or a train id, ``roi`` an id or a name of :data:`ROI_NAMES`.

    >>> print(paper_table([{"matrix": "egoistic", "class": "person", "roi": 1,
    ...                     "precision": 0.9, "recall": float("nan")}]))
    | class | RoI | matrix | precision | recall | paper precision | paper recall |
    |---|---|---|---|---|---|---|
    | person | 1 street | egoistic | 90.00 | nan | 93.88 | 70.07 |
    """
    _check_rows(rows)
    classes = list(dict.fromkeys(_class_name(r["class"]) for r in rows))
    rois = list(dict.fromkeys(_roi_id(r["roi"]) for r in rows))
    ordered = sorted(
        rows, key=lambda r: (classes.index(_class_name(r["class"])), rois.index(_roi_id(r["roi"])))
    )
    extra = [c for c in EXTRA_COLUMNS if any(c in r for r in rows)]
    defer = [DEFER_COLUMN] if any(DEFER_COLUMN in r for r in rows) else []
    with_paper = any(_key(r) in _PAPER for r in rows)
    table, previous = [], ("", "")
    for r in ordered:
        group = (_class_name(r["class"]), _roi_label(r["roi"]))
        shown = ("" if group[0] == previous[0] else group[0], "" if group == previous else group[1])
        previous = group
        paper = _PAPER.get(_key(r), {})
        table.append({**r, "class": shown[0], "roi": shown[1], **_paper_fractions(paper)})
    columns = ["class", "roi", "matrix", *defer, *PAPER_RATES, *extra]
    columns += list(_PAPER_RATES) if with_paper else []
    headers = ["RoI" if c == "roi" else c for c in columns]
    return markdown_table(table, columns, headers, percent=_PERCENT_WITH_PAPER)


def _check_rows(rows: Sequence[Row]) -> None:
    for r in rows:
        missing = [k for k in PAPER_COLUMNS if k not in r]
        if missing:
            raise ValueError(
                f"each row needs {', '.join(PAPER_COLUMNS)}; row {r} lacks {', '.join(missing)}"
            )
        if r["roi"] not in ROI_NAMES and r["roi"] not in range(NUM_ROIS + 1):
            raise ValueError(
                f"expected roi in 0..{NUM_ROIS} or one of {ROI_NAMES}, got {r['roi']!r}"
            )
        if r["class"] not in CLASS_NAMES and r["class"] not in range(NUM_CLASSES):
            raise ValueError(
                f"expected a class name or train id 0..{NUM_CLASSES - 1}, got {r['class']!r}"
            )


def compare_with_paper(rows: Sequence[Row]) -> str:
    """Markdown table of the paper's 12 rows (docs/definitions.md §5) next to the measured values.

    Measured precision/recall come from the row with the same (matrix, class, RoI), matched
    case-insensitively on the matrix name; ``—`` where none was measured.

    >>> table = compare_with_paper([{"matrix": "Altruistic", "class": 11, "roi": "street",
    ...                              "precision": 0.5, "recall": 1.0}])
    >>> print(table.splitlines()[2])
    | altruistic | person | 1 street | 50.00 | 100.00 | 41.12 | 99.81 |
    """
    _check_rows(rows)
    measured = {_key(r): r for r in rows}
    table = []
    for p in PAPER_TABLE:
        m = measured.get(_key(p), {})
        table.append(
            {
                "matrix": p["matrix"],
                "class": p["class"],
                "roi": _roi_label(p["roi"]),
                **{k: m.get(k) for k in PAPER_RATES},
                **_paper_fractions(p),
            }
        )
    columns = [*PAPER_COLUMNS, *_PAPER_RATES]
    headers = ["matrix", "class", "RoI", *columns[3:]]
    return markdown_table(table, columns, headers, percent=_PERCENT_WITH_PAPER)
