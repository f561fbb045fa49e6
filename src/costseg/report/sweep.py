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

from costseg.classes import CLASS_NAMES, ROI_NAMES
from costseg.costs import save_cost
from costseg.metrics.names import PAPER_RATES, PIXEL_RATES, SEGMENT_RATES
from costseg.metrics.selection import choose
from costseg.report.curves import Curves, curve_figures
from costseg.report.drawing import Job, job
from costseg.report.files import write_csv, write_json
from costseg.report.results import EvalResults, GroupResult
from costseg.report.risk_coverage import write_risk_coverage
from costseg.report.tables import PAPER_ROIS
from costseg.report.ternary import edge_tradeoff_figures, ternary_figures
from costseg.rules import DEFER_FAMILY

SWEEP_ROIS = (0, *PAPER_ROIS)
"""The RoIs of a sweep's rows: the whole image and the paper's."""


def write_sweeps(results: EvalResults) -> list[tuple[str, Job]]:
    """Files of every sweeping group and the ``--target`` answer; returns their figures,
    undrawn, as ``(TensorBoard prefix, job)`` (:mod:`costseg.report.drawing`)."""
    batches: list[tuple[str, Job]] = []
    for result in results.groups:
        group, out = result.group, results.output_dir
        if group.output is None:
            continue
        if group.family == DEFER_FAMILY:  # its curves run along coverage (risk–coverage)
            batches += write_risk_coverage(results, result)
            continue
        rows = result.rows(results.class_ids, SWEEP_ROIS)
        write_csv(out / f"{group.output}.csv", rows)
        record = {"note": group.note, "probabilities": results.probabilities, "rows": rows}
        write_json(out / f"{group.output}.json", record)
        if group.weights is not None:
            batches += _triangle_figures(results, result)
        if group.line is not None:
            batches.append(
                (group.output, job(curve_figures, _line_curves(results, result), results.subject))
            )
    candidates = next((r for r in results.groups if r.group.candidates), None)
    if results.options.get("target") and candidates is not None:
        _write_choice(results, candidates)
    return batches


def _triangle_figures(results: EvalResults, grid: GroupResult) -> list[tuple[str, Job]]:
    group, pixels, segments = grid.group, grid.pixels, grid.segments
    labels = tuple(v.capitalize() for v in group.corners)
    ternary, edges = [], []
    for c, cls in enumerate(results.class_ids):
        name = CLASS_NAMES[cls]
        for roi in PAPER_ROIS:
            for metric in PIXEL_RATES:
                values, title = pixels[metric][:, roi, cls], f"{metric} of {name}, RoI {roi}"
                ternary.append((f"ternary_{name}_roi{roi}_{metric}", values, title, metric))
            precision, recall = (pixels[m][:, roi, cls] for m in PAPER_RATES)
            title = f"precision and recall of {name} in RoI {roi} ({ROI_NAMES[roi]})"
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
         f"instance recall of {name}, RoI {roi}", "instance recall")
        for roi in (1, 2)
    ]  # fmt: skip


def _write_choice(results: EvalResults, result: GroupResult) -> None:
    opts, out, group = results.options, results.output_dir, result.group
    choice = choose(
        result.pixels,
        result.segments,
        opts["target"],
        opts["maximize"],
        results.class_ids,
        result.instances,
        group.prefer,
    )
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
