"""Outputs of the value-space sweep and of the prior-adapted α sweep.

``sweep.csv`` / ``sweep.json`` hold every grid point; ``figures/ternary_*.png`` the paper-style
triangles; ``figures/edges_*.png`` the precision–recall trade-off along each edge; with
``--target``, ``best.json`` and ``best_cost.yaml`` the chosen value system.
"""

from __future__ import annotations

from collections.abc import Iterator

from costseg.classes import CLASS_NAMES
from costseg.costs import mix_costs, save_cost
from costseg.report.curves import plot_curves
from costseg.report.drawing import Batch
from costseg.report.files import write_csv, write_json
from costseg.report.ternary import edge_tradeoff_figures, ternary_figures
from costseg.results import EvalResults, GroupResult
from costseg.selection import choose

SWEEP_ROIS = (0, 1, 2)


def write_sweeps(results: EvalResults) -> list[tuple[str, Batch]]:
    """Files of the grid and α groups, if evaluated, and the ``--target`` answer; returns their
    figures, undrawn, as ``(TensorBoard prefix, batch)`` (:mod:`costseg.report.drawing`)."""
    grid, alpha = results.group("grid"), results.group("alpha")
    batches = [] if grid is None else _write_grid(results, grid)
    return batches + ([] if alpha is None else _write_alpha(results, alpha))


def _write_grid(results: EvalResults, grid: GroupResult) -> list[tuple[str, Batch]]:
    out, note, weights = results.output_dir, grid.group.note, grid.group.weights
    rows = grid.rows(results.class_ids, SWEEP_ROIS)
    write_csv(out / "sweep.csv", rows)
    write_json(
        out / "sweep.json", {"note": note, "probabilities": results.probabilities, "rows": rows}
    )
    labels = tuple(v.capitalize() for v in results.options["vertices"])
    pixels, segments = grid.pixels, grid.segments
    ternary, edges = [], []
    for c, cls in enumerate(results.class_ids):
        name = CLASS_NAMES[cls]
        for roi in (1, 2):
            precision, recall = pixels["precision"][:, roi, cls], pixels["recall"][:, roi, cls]
            for metric, values in (("precision", precision), ("recall", recall)):
                title = f"{metric} of {name}, RoI {roi}"
                ternary.append((f"ternary_{name}_roi{roi}_{metric}", values, title, metric))
            edges.append((f"edges_{name}_roi{roi}", precision, recall))
        for metric in ("fp_rate", "fn_rate"):
            title = f"{metric.replace('_', ' ')} of {name} segments"
            ternary.append((f"ternary_{name}_{metric}", segments[metric][:, c, 0], title, metric))
        ternary += _instance_ternaries(grid, cls)
    if results.options.get("target"):
        _write_choice(results, grid)
    return [
        ("sweep", ternary_figures(weights, ternary, labels, note=note)),
        ("sweep", edge_tradeoff_figures(weights, edges, labels, note=note)),
    ]


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


def _write_choice(results: EvalResults, grid: GroupResult) -> None:
    opts, out = results.options, results.output_dir
    choice = choose(
        grid.pixels,
        grid.segments,
        opts["target"],
        opts["maximize"],
        results.class_ids,
        grid.instances,
    )
    record = {
        "target": choice.target,
        "maximize": choice.maximize,
        "measured_on": "the same images",
    }
    if not choice.points:
        print(
            f"no grid point meets {choice.target} (the best on the grid: {choice.best_reached:.4f})"
        )
        write_json(out / "best.json", {**record, "found": False, "best": choice.best_reached})
        return
    points = [grid.group.columns[k] for k in choice.points]
    matrix = mix_costs(grid.group.vertices, grid.group.weights[choice.points[:1]])[0]
    save_cost(out / "best_cost.yaml", matrix, "best")
    print(
        f"{len(points)} grid point(s) meet {choice.target} with the largest {choice.maximize} "
        f"= {choice.value:.4f}: {points}; cost matrix of the first: {out / 'best_cost.yaml'}"
    )
    write_json(
        out / "best.json",
        {
            **record,
            "found": True,
            "value": choice.value,
            "points": points,
            "matrix": matrix.tolist(),
        },
    )


def _write_alpha(results: EvalResults, alpha: GroupResult) -> list[tuple[str, Batch]]:
    out = results.output_dir
    alphas = [c["prior_alpha"] for c in alpha.group.columns]
    rows = alpha.rows(results.class_ids, SWEEP_ROIS)
    write_csv(out / "alpha_sweep.csv", rows)
    write_json(out / "alpha_sweep.json", {"note": alpha.group.note, "rows": rows})
    return [("alpha_sweep", _alpha_figures(results, alpha, alphas))]


def _alpha_figures(results: EvalResults, alpha: GroupResult, alphas: list) -> Iterator[tuple]:
    for cls in results.class_ids:
        name = CLASS_NAMES[cls]
        series = {
            f"{metric} RoI {roi}": alpha.pixels[metric][:, roi, cls].tolist()
            for roi in (1, 2)
            for metric in ("precision", "recall")
        }
        yield (
            f"alpha_{name}",
            plot_curves(
                alphas,
                series,
                "α (0 = Bayes, 1 = maximum likelihood)",
                f"{name}: {alpha.group.note}",
            ),
        )
