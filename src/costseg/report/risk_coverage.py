"""The outputs of ``--defer_sweep`` (docs/definitions.md §14): risk–coverage curves and AURC.

Each rule of ``--cost`` is one path of the defer-sweep group (``RuleGroup.paths``, from its
smallest defer cost up). Per class and RoI its curve is the coverage against the selective error
``1 − selective_recall``; over all classes of a RoI, ``1 − deferred_rate`` against
``1 − selective pixel accuracy``. ``defer_sweep.csv`` / ``.json`` hold every point with these
columns, ``figures/risk_coverage_<class>.png`` one curve per rule in RoIs 0–2, TensorBoard the
curves along the defer costs, and results.json / table.md the area under each (AURC).
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence

from costseg.classes import CLASS_NAMES, roi_label
from costseg.metrics.functional.deferral import risk_coverage_area, selective_error
from costseg.report.curves import Panel, risk_coverage_figures
from costseg.report.drawing import job
from costseg.report.files import write_csv, write_json
from costseg.report.results import EvalResults, GroupResult
from costseg.report.sections import Section
from costseg.report.tables import PAPER_ROIS, format_value

CURVE_ROIS = (0, *PAPER_ROIS)
"""The RoIs of the curves: the whole image and the paper's."""

ALL = "all"
"""The curve over all classes of a RoI (the class of ``all:roiN:coverage``)."""

Curve = tuple[list[float], list[float]]  # coverage, risk along one rule's defer costs


def curve(result: GroupResult, path: Sequence[int], cls: int | str, roi: int) -> Curve:
    """(coverage, risk) of one rule (its ``path`` of rule indices) for class ``cls`` (or
    :data:`ALL`) in RoI ``roi``; NaN where undefined."""
    pixels, path = result.pixels, list(path)
    if cls == ALL:
        coverage = pixels["coverage_all_classes"][path, roi]
        risk = selective_error(pixels["confmat"][path, roi])
    else:
        coverage = pixels["coverage"][path, roi, cls]
        risk = 1 - pixels["selective_recall"][path, roi, cls]
    return coverage.tolist(), risk.tolist()


def areas(result: GroupResult, class_ids: Sequence[int]) -> dict[str, dict[str, dict]]:
    """AURC per rule → class (and ``all``) → ``roi<r>``."""
    group, out = result.group, {}
    for path in group.paths:
        keys = [*(CLASS_NAMES[c] for c in class_ids), ALL]
        classes = [*class_ids, ALL]
        out[group.rules[path[0]].name] = {
            key: {f"roi{r}": risk_coverage_area(*curve(result, path, c, r)) for r in CURVE_ROIS}
            for key, c in zip(keys, classes, strict=True)
        }
    return out


def curve_rows(result: GroupResult, class_ids: Sequence[int]) -> list[dict]:
    """The rows of ``defer_sweep.csv``: every rule × defer cost × class × RoI with the
    selective error, and the RoI's coverage and selective error over all classes."""
    pixels, rows = result.pixels, result.rows(class_ids, CURVE_ROIS)
    per_rule = len(class_ids) * len(CURVE_ROIS)  # rows() goes rule by rule
    for i, row in enumerate(rows):
        k, r = i // per_rule, row["roi"]
        row["selective_error"] = 1 - row["selective_recall"]
        row["coverage_all_classes"] = pixels["coverage_all_classes"][k, r].item()
        row["selective_error_all_classes"] = selective_error(pixels["confmat"][k, r]).item()
    return rows


def risk_coverage_outputs(results: EvalResults, mine: list[GroupResult]) -> Section:
    """The defer sweep's outputs: ``defer_sweep.csv`` / ``.json``, the AURC in results.json
    and table.md, the figures and the TensorBoard curves."""
    (result,) = mine
    group, out = result.group, results.output_dir
    rows = curve_rows(result, results.class_ids)
    write_csv(out / f"{group.output}.csv", rows)
    layout = "[rule][class, or all: over every class][RoI] area under coverage vs selective error"
    record = {"risk_coverage_area": {"layout": layout, **areas(result, results.class_ids)}}
    json = {"note": group.note, "probabilities": results.probabilities, "rows": rows}
    write_json(out / f"{group.output}.json", json | record)
    panels = risk_coverage_panels(result, results.class_ids)
    note = "; ".join(filter(None, (group.note, results.subject)))
    return Section(
        json=record,
        table=f"\n{_table(result, results.class_ids)}\n",
        jobs=[(group.output, job(risk_coverage_figures, panels, note))],
        curves=list(risk_coverage_curves(result, results.class_ids)),
    )


def _table(result: GroupResult, class_ids: Sequence[int]) -> str:
    """The AURC table of table.md."""
    head = " | ".join(roi_label(r) for r in CURVE_ROIS)
    lines = [
        f"| {rule} | {key} | " + " | ".join(format_value(v) for v in by_roi.values()) + " |"
        for rule, by_class in areas(result, class_ids).items()
        for key, by_roi in by_class.items()
    ]
    return "\n".join(
        [
            "## Risk–coverage: area under coverage vs selective error (AURC, lower is better)",
            "",
            f"{result.group.note}; class {ALL}: every class of the RoI (1 − pixel accuracy).",
            "",
            f"| matrix | class | {head} |",
            "|---|---|" + "---|" * len(CURVE_ROIS),
            *lines,
        ]
    )


def risk_coverage_panels(result: GroupResult, class_ids: Sequence[int]) -> list[list[Panel]]:
    """Per class (and :data:`ALL`), the panels of its figure: per RoI, one curve per rule."""
    group, figures = result.group, []
    for cls in [*class_ids, ALL]:
        name, panels = (cls if cls == ALL else CLASS_NAMES[cls]), []
        for roi in CURVE_ROIS:
            curves = []
            for path in group.paths:
                coverage, risk = curve(result, path, cls, roi)
                area = format_value(risk_coverage_area(coverage, risk))
                curves.append((f"{group.rules[path[0]].name} (AURC {area})", (coverage, risk)))
            panels.append((name, f"{name}, {roi_label(roi)}", curves))
        figures.append(panels)
    return figures


def risk_coverage_curves(result: GroupResult, class_ids: Sequence[int]) -> Iterator[tuple]:
    """TensorBoard curves along each rule's defer costs (step k: its k-th defer cost):
    ``defer_sweep/<rule>/{coverage,selective_error,handled_recall}_roi<r>`` per class (run),
    and the RoI's coverage and selective error over all classes (no run)."""
    group, pixels = result.group, result.pixels
    for path in group.paths:
        rule, steps = group.rules[path[0]].name, list(range(len(path)))
        for roi in CURVE_ROIS:
            tag = f"{group.output}/{rule}/{{}}_roi{roi}"
            for cls in class_ids:
                coverage, risk = curve(result, path, cls, roi)
                handled = pixels["handled_recall"][list(path), roi, cls].tolist()
                series = {"coverage": coverage, "selective_error": risk, "handled_recall": handled}
                for metric, values in series.items():
                    yield tag.format(metric), CLASS_NAMES[cls], steps, values
            coverage, risk = curve(result, path, ALL, roi)
            yield tag.format("coverage"), None, steps, coverage
            yield tag.format("selective_error"), None, steps, risk
