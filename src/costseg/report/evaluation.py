"""Everything ``evaluate.py`` writes for the named rules: tables, JSON/CSV, figures, TensorBoard.

The evaluation directory holds ``table.md`` (the paper's layout, next to the paper's numbers),
``results.csv`` / ``results.json``, ``figures/*.png`` and the TensorBoard events.
"""

from __future__ import annotations

from pathlib import Path

from torch.utils.tensorboard import SummaryWriter

from costseg.classes import CLASS_NAMES
from costseg.report.figures import plot_cost_matrix, plot_heatmap_grid, plot_masks, plot_roi_map
from costseg.report.files import save_figure, write_csv, write_json, write_text
from costseg.report.tables import ROI_NAMES, compare_with_paper, console_table, paper_table
from costseg.report.tensorboard import log_figures, log_masks, log_scalars, log_table

SUMMARY_COLUMNS = ("matrix", "class", "roi", "precision", "recall", "fp_segments", "fn_segments")


def write_outputs(out_dir, opts, module, groups, results, rows, class_ids, info, examples) -> None:
    """Write the named rules' results (and the sweeps', see ``report.sweep``) into ``out_dir``."""
    from costseg.report.sweep import write_alpha_sweep, write_sweep

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    figures_dir = out_dir / "figures"
    names = groups[0].names
    headline = [r for r in rows if r["roi"] in (1, 2)]
    print(console_table(headline, SUMMARY_COLUMNS))
    print(
        "mIoU: "
        + ", ".join(f"{n} {100 * results[0]['pixels']['miou'][k]:.2f}" for k, n in enumerate(names))
    )
    tables = _tables(rows, headline, names, results[0])
    write_text(out_dir / "table.md", tables)
    write_csv(out_dir / "results.csv", rows)
    write_json(out_dir / "results.json", _json(opts, rows, names, results[0], module))
    figures = _figures(module, info["rules"], results[0], class_ids, examples)
    for tag, fig in figures.items():
        save_figure(fig, figures_dir / f"{tag.replace('/', '_')}.png")
    with SummaryWriter(str(out_dir)) as writer:
        log_table(writer, "evaluation/table", tables)
        log_scalars(writer, _scalars(rows, names, results[0]))
        for i, (image, label, preds) in enumerate(examples):
            log_masks(
                writer,
                f"evaluation/masks/{i}",
                image.permute(1, 2, 0).numpy(),
                label.numpy(),
                {n: preds[k].numpy() for k, n in enumerate(names)},
            )
        log_figures(writer, {f"evaluation/{t}": f for t, f in figures.items()})
        if "sweep" in info:
            write_sweep(out_dir, writer, opts, results[info["sweep"]], class_ids, info)
        if "alpha" in info:
            write_alpha_sweep(out_dir, writer, results[info["alpha"]], class_ids, info)
    print(f"results written to {out_dir}")


def _tables(rows, headline, names, result) -> str:
    miou = "\n".join(
        f"| {n} | {100 * result['pixels']['miou'][k]:.2f} |" for k, n in enumerate(names)
    )
    return "\n\n".join(
        [
            "# Precision and recall per cost matrix (RoI 1 = street, 2 = sidewalk)",
            paper_table(headline),
            f"## mIoU (19 classes)\n\n| matrix | mIoU |\n|---|---|\n{miou}",
            "## Next to the paper (Cityscapes val, DeepLabv3+ Xception)",
            compare_with_paper(headline) + "\n",
        ]
    )


def _json(opts, rows, names, result, module) -> dict:
    pixels = result["pixels"]
    return {
        "options": vars(opts),
        "vertex_scaling": "none (matrices as defined in configs/costs)",
        "rois": list(ROI_NAMES),
        "rows": rows,
        "miou": {n: pixels["miou"][k].item() for k, n in enumerate(names)},
        "iou": {
            n: dict(zip(CLASS_NAMES, pixels["iou"][k].tolist(), strict=False))
            for k, n in enumerate(names)
        },
        "confusion_matrix": {
            "layout": "[rule][true class][predicted class], whole image, pixels",
            **{n: pixels["confmat"][k, 0].tolist() for k, n in enumerate(names)},
        },
        "model": dict(module.hparams),
    }


def _scalars(rows, names, result) -> dict[str, float]:
    scalars = {
        f"evaluation/miou/{n}": result["pixels"]["miou"][k].item() for k, n in enumerate(names)
    }
    for r in rows:
        base = f"evaluation/{r['class']}/roi{r['roi']}"
        scalars[f"{base}/precision/{r['matrix']}"] = r["precision"]
        scalars[f"{base}/recall/{r['matrix']}"] = r["recall"]
        scalars[f"{base}/fp_segments/{r['matrix']}"] = r["fp_segments"]
        scalars[f"{base}/fn_segments/{r['matrix']}"] = r["fn_segments"]
    return scalars


def _figures(module, rules, result, class_ids, examples) -> dict:
    names = [r.name for r in rules]
    segments = result["segments"]
    figures = {}
    for kind, key in (("FP", "fp_map"), ("FN", "fn_map")):
        maps = {
            (n, CLASS_NAMES[cls]): segments[key][k, c].cpu().numpy()
            for k, n in enumerate(names)
            for c, cls in enumerate(class_ids)
        }
        figures[f"{kind.lower()}_segments"] = plot_heatmap_grid(maps, kind=kind)
    for i, (image, label, preds) in enumerate(examples):
        figures[f"masks_{i}"] = plot_masks(
            image.permute(1, 2, 0).numpy(),
            label.numpy(),
            {n: preds[k].numpy() for k, n in enumerate(names)},
        )
    for rule in rules:
        if rule.cost is not None:
            figures[f"cost_{rule.name}"] = plot_cost_matrix(rule.cost, CLASS_NAMES, rule.name)
    if module.priors is not None:
        figures["roi_map"] = plot_roi_map(module.priors_at(tuple(module.priors.shape[1:]))[1].cpu())
    return figures
