"""Outputs of the value-space sweep and of the prior-adapted α sweep.

``sweep.csv`` / ``sweep.json`` hold every grid point; ``figures/ternary_*.png`` the paper-style
triangles; ``figures/edges_*.png`` the precision–recall trade-off along each edge; with
``--target``, ``best.json`` and ``best_cost.yaml`` the chosen value system.
"""

from __future__ import annotations

import math

from costseg.classes import CLASS_NAMES
from costseg.costs import mix_costs, save_cost
from costseg.report.curves import plot_curves
from costseg.report.files import save_figure, write_csv, write_json
from costseg.report.tensorboard import log_figures
from costseg.report.ternary import plot_edge_tradeoffs, plot_ternary
from costseg.sweep import best_points, metric_values, parse_metric, parse_target

METRIC_KEYS = ("precision", "recall", "fp_rate", "fn_rate")


def sweep_rows(result, class_ids, weights=None, alphas=None) -> list[dict]:
    """One row per point × class × RoI (0, 1, 2) with pixel and segment metrics."""
    pixels, segments = result["pixels"], result["segments"]
    rows = []
    for k in range(pixels["precision"].shape[0]):
        point = (
            dict(zip(("alpha", "beta", "gamma"), weights[k].tolist(), strict=True))
            if weights is not None
            else {"prior_alpha": alphas[k]}
        )
        for c, cls in enumerate(class_ids):
            for r in (0, 1, 2):
                rows.append(
                    {
                        **point,
                        "class": CLASS_NAMES[cls],
                        "roi": r,
                        "precision": pixels["precision"][k, r, cls].item(),
                        "recall": pixels["recall"][k, r, cls].item(),
                        "fp_rate": segments["fp_rate"][k, c, r].item(),
                        "fn_rate": segments["fn_rate"][k, c, r].item(),
                        "miou": pixels["miou"][k].item(),
                    }
                )
    return rows


def write_sweep(out_dir, writer, opts, result, class_ids, info) -> None:
    """Files, ternary heatmaps, edge trade-offs and the ``--target`` answer of a grid sweep."""
    weights = info["weights"]
    note = f"vertices: {', '.join(opts.vertices)}; vertex scaling: {opts.vertex_scaling}"
    rows = sweep_rows(result, class_ids, weights=weights)
    write_csv(out_dir / "sweep.csv", rows)
    write_json(out_dir / "sweep.json", {"vertices": opts.vertices, "note": note, "rows": rows})
    labels = tuple(v.capitalize() for v in opts.vertices)
    figures = {}
    pixels, segments = result["pixels"], result["segments"]
    for c, cls in enumerate(class_ids):
        name = CLASS_NAMES[cls]
        for roi in (1, 2):
            for metric in ("precision", "recall"):
                values = pixels[metric][:, roi, cls]
                figures[f"ternary_{name}_roi{roi}_{metric}"] = plot_ternary(
                    weights, values, labels, f"{metric} of {name}, RoI {roi}", metric, note=note
                )
            figures[f"edges_{name}_roi{roi}"] = plot_edge_tradeoffs(
                weights,
                pixels["precision"][:, roi, cls],
                pixels["recall"][:, roi, cls],
                labels,
                note=note,
            )
        for metric in ("fp_rate", "fn_rate"):
            figures[f"ternary_{name}_{metric}"] = plot_ternary(
                weights,
                segments[metric][:, c, 0],
                labels,
                f"{metric.replace('_', ' ')} of {name} segments",
                metric,
                note=note,
            )
    for tag, fig in figures.items():
        save_figure(fig, out_dir / "figures" / f"{tag}.png")
    log_figures(writer, {f"sweep/{t}": f for t, f in figures.items()})
    if opts.target:
        _answer_target(out_dir, opts, result, class_ids, info)


def _answer_target(out_dir, opts, result, class_ids, info) -> None:
    target, goal = parse_target(opts.target), parse_metric(opts.maximize)
    position = {cls: c for c, cls in enumerate(class_ids)}
    target_values = metric_values(result, target, position.get(target.cls))
    values = metric_values(result, goal, position.get(goal.cls))
    winners = best_points(values, target_values, target)
    if not winners:
        reached = target_values[~target_values.isnan()]
        best = reached.max().item() if len(reached) else math.nan
        print(f"no grid point meets {opts.target} (the best on the grid: {best:.4f})")
        write_json(out_dir / "best.json", {"target": opts.target, "found": False, "best": best})
        return
    weights = info["weights"][winners]
    matrix = mix_costs(info["vertices"], weights[:1])[0]
    save_cost(out_dir / "best_cost.yaml", matrix, "best")
    points = [dict(zip(("alpha", "beta", "gamma"), w, strict=True)) for w in weights.tolist()]
    top = values[winners[0]].item()
    print(
        f"{len(winners)} grid point(s) meet {opts.target} with the largest {opts.maximize} "
        f"= {top:.4f}: {points}; cost matrix of the first: {out_dir / 'best_cost.yaml'}"
    )
    write_json(
        out_dir / "best.json",
        {
            "target": opts.target,
            "maximize": opts.maximize,
            "found": True,
            "value": top,
            "points": points,
            "matrix": matrix.tolist(),
        },
    )


def write_alpha_sweep(out_dir, writer, result, class_ids, info) -> None:
    """Files and precision/recall-vs-α curves of the prior-adapted rule."""
    alphas = info["alphas"]
    rows = sweep_rows(result, class_ids, alphas=alphas)
    write_csv(out_dir / "alpha_sweep.csv", rows)
    write_json(out_dir / "alpha_sweep.json", {"cost": info["alpha_label"], "rows": rows})
    figures = {}
    for cls in class_ids:
        name = CLASS_NAMES[cls]
        series = {
            f"{metric} RoI {roi}": result["pixels"][metric][:, roi, cls].tolist()
            for roi in (1, 2)
            for metric in ("precision", "recall")
        }
        figures[f"alpha_{name}"] = plot_curves(
            alphas,
            series,
            "α (0 = Bayes, 1 = maximum likelihood)",
            f"{name}: {info['alpha_label']} on p/π_α",
        )
    for tag, fig in figures.items():
        save_figure(fig, out_dir / "figures" / f"{tag}.png")
    log_figures(writer, {f"alpha_sweep/{t}": f for t, f in figures.items()})
