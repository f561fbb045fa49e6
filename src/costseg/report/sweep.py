"""Outputs of the groups that sweep many rules (the value-space grid, the α path, any other).

Each such group (``RuleGroup.output`` set) gets ``<output>.csv`` / ``<output>.json`` with every
rule's rows, and its figures from where its rules lie: rules in the value triangle
(``weights``) give the paper-style triangles ``figures/ternary_*.png`` and the precision–recall
trade-off along each edge ``figures/edges_*.png``; rules along one axis (``line``) give curves;
the defer sweep gives risk–coverage curves (:mod:`costseg.report.risk_coverage`).
With ``--target``, ``best.json`` (and ``best_cost.yaml`` when the rule is a cost matrix) answer
it over the first group of candidates.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from dataclasses import dataclass

from costseg.classes import CLASS_NAMES, roi_label
from costseg.costs import save_cost
from costseg.metrics.names import PAPER_RATES, PIXEL_RATES, SEGMENT_RATES
from costseg.metrics.selection import choose
from costseg.report.curves import Curves, curve_figures
from costseg.report.drawing import Job, job
from costseg.report.files import write_csv, write_json
from costseg.report.results import EvalResults, GroupResult
from costseg.report.sections import Curve, Result, Section
from costseg.report.tables import PAPER_ROIS
from costseg.report.ternary import edge_tradeoff_figures, ternary_figures

SWEEP_ROIS = (0, *PAPER_ROIS)
"""The RoIs of a sweep's rows: the whole image and the paper's (and those a target or
requirement names)."""


def sweep_outputs(results: EvalResults, mine: list[GroupResult]) -> Section:
    """``<output>.csv`` / ``.json`` of each group of ``mine`` that has an output; its figures
    (triangles or curves) and TensorBoard curves along its rules."""
    section = Section()
    for result in mine:
        group, out = result.group, results.output_dir
        if group.output is None:
            continue
        rois = tuple(sorted({*SWEEP_ROIS, *results.rois}))
        rows = result.rows(results.class_ids, rois)
        write_csv(out / f"{group.output}.csv", rows)
        record = {"note": group.note, "probabilities": results.probabilities, "rows": rows}
        write_json(out / f"{group.output}.json", record)
        if group.weights is not None:
            section.jobs += _triangle_figures(results, result)
        if group.line is not None:
            curves = _line_curves(results, result)
            section.jobs.append((group.output, job(curve_figures, curves, results.subject)))
        section.curves += list(_tensorboard_curves(result, results.class_ids))
    return section


def _tensorboard_curves(result: GroupResult, class_ids: Sequence[int]) -> Iterator[Curve]:
    """mIoU, each pixel rate of each class in RoI 1 and 2, and the segment rates, along the
    group's rules (step: the rule's index)."""
    prefix, steps = result.group.output, list(range(len(result.group.names)))
    yield f"{prefix}/miou", None, steps, result.pixels["miou"].tolist()
    for cls in class_ids:
        for roi in (1, 2):
            for metric in PIXEL_RATES:
                values = result.pixels[metric][:, roi, cls].tolist()
                yield f"{prefix}/{metric}_roi{roi}", CLASS_NAMES[cls], steps, values
    for c, cls in enumerate(class_ids):
        for metric in SEGMENT_RATES:
            if result.segments and metric in result.segments:
                values = result.segments[metric][:, c, 0].tolist()
                yield f"{prefix}/{metric}", CLASS_NAMES[cls], steps, values


@dataclass
class SweepPoint(Result):
    """``--target`` / ``--maximize``: the points of the first group of candidates that meet
    the target on the reported images, the best of them by the objective."""

    target: str
    maximize: str

    def write(self, results: EvalResults) -> Section:
        """``best.json`` (and ``best_cost.yaml``) with the answer."""
        candidates = next((r for r in results.groups if r.group.candidates), None)
        if candidates is not None:
            _write_choice(results, candidates, self)
        return Section()

    def points(self, results: EvalResults, result: GroupResult) -> list[int]:
        """The indices of ``result``'s rules chosen (none when none meets the target)."""
        return self.chosen(results, result).points

    def chosen(self, results: EvalResults, result: GroupResult):
        """The choice (:func:`costseg.metrics.selection.choose`) among ``result``'s rules."""
        return choose(
            result.pixels,
            result.segments,
            self.target,
            self.maximize,
            results.class_ids,
            result.instances,
            result.group.prefer,
        )


def _triangle_figures(results: EvalResults, grid: GroupResult) -> list[tuple[str, Job]]:
    group, pixels, segments = grid.group, grid.pixels, grid.segments
    labels = tuple(v.capitalize() for v in group.corners)
    ternary, edges = [], []
    for c, cls in enumerate(results.class_ids):
        name = CLASS_NAMES[cls]
        for roi in PAPER_ROIS:
            for metric in PIXEL_RATES:
                title = f"{metric} of {name} in {roi_label(roi)}"
                values = pixels[metric][:, roi, cls]
                ternary.append((f"ternary_{name}_roi{roi}_{metric}", values, title, metric))
            precision, recall = (pixels[m][:, roi, cls] for m in PAPER_RATES)
            title = f"precision and recall of {name} in {roi_label(roi)}"
            edges.append((f"edges_{name}_roi{roi}", precision, recall, title))
        for metric in SEGMENT_RATES:
            title = f"{metric.replace('_', ' ')} of {name} segments"
            ternary.append((f"ternary_{name}_{metric}", segments[metric][:, c, 0], title, metric))
        ternary += _instance_ternaries(grid, cls)
    note = "; ".join(filter(None, (group.note, results.subject)))
    return [
        (group.output, job(ternary_figures, group.weights, ternary, labels, note=note)),
        (group.output, job(edge_tradeoff_figures, group.weights, edges, labels, note=note)),
    ]


def _line_curves(results: EvalResults, result: GroupResult) -> list[Curves]:
    group, curves = result.group, []
    for cls in results.class_ids:
        name = CLASS_NAMES[cls]
        series = {
            f"{metric} RoI {roi}": result.pixels[metric][:, roi, cls].tolist()
            for roi in PAPER_ROIS
            for metric in PIXEL_RATES
        }
        title = f"{name}: {group.note}"
        curves.append((f"{group.family}_{name}", list(group.line), series, group.axis, title))
    return curves


def _instance_ternaries(grid: GroupResult, cls: int) -> list[tuple]:
    """Ternary heatmaps of the instance recall of ``cls`` in RoIs 1 and 2, where measured."""
    measured = grid.instances["classes"].tolist() if grid.instances else []
    if cls not in measured:
        return []
    name, recall = CLASS_NAMES[cls], grid.instances["instance_recall"][:, measured.index(cls)]
    return [
        (f"ternary_{name}_roi{roi}_instance_recall", recall[:, roi],
         f"instance recall of {name} in {roi_label(roi)}", "instance recall")
        for roi in (1, 2)
    ]  # fmt: skip


def _write_choice(results: EvalResults, result: GroupResult, point: SweepPoint) -> None:
    out, group = results.output_dir, result.group
    choice = point.chosen(results, result)
    record = {
        "target": choice.target,
        "maximize": choice.maximize,
        "measured_on": "the same images",
    }
    if not choice.points:
        print(
            f"no {group.family} point meets {choice.target} "
            f"(the best among them: {choice.best_reached:.4f})"
        )
        write_json(out / "best.json", {**record, "found": False, "best": choice.best_reached})
        return
    points = [group.columns[k] for k in choice.points]
    matrix = group.cost(choice.points[0])
    where = ""
    record |= {"found": True, "value": choice.value, "points": points}
    if matrix is not None:
        save_cost(out / "best_cost.yaml", matrix, "best")
        record["matrix"] = matrix.tolist()
        where = f"; cost matrix of the first: {out / 'best_cost.yaml'}"
    print(
        f"{len(points)} {group.family} point(s) meet {choice.target} with the largest "
        f"{choice.maximize} = {choice.value:.4f}: {points}{where}"
    )
    write_json(out / "best.json", record)
