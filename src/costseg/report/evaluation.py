"""Everything ``evaluate.py`` writes: tables, JSON/CSV, figures, TensorBoard.

The evaluation folder holds ``table.md`` (the paper's layout, next to the paper's numbers),
``results.csv`` / ``results.json``, ``figures/*.png`` and the TensorBoard events; the sweeps add
theirs (:mod:`costseg.report.sweep`).
"""

from __future__ import annotations

from typing import Any

from torch.utils.tensorboard import SummaryWriter

from costseg.classes import CLASS_NAMES, ROI_NAMES
from costseg.metrics.names import DEFER_RULE_RATES, ERROR_COLUMNS, INSTANCE_COLUMNS
from costseg.report.anomalies import anomaly_jobs, anomaly_json, anomaly_table, log_anomalies
from costseg.report.drawing import Drawing, Job, figure_path, job
from costseg.report.early_figures import EarlyFigures, example_figures, mask_names, plan_figures
from costseg.report.figures import heatmap_grid_figures
from costseg.report.files import write_csv, write_json, write_text
from costseg.report.results import EvalResults, GroupResult
from costseg.report.risk_coverage import risk_coverage_json, risk_coverage_table
from costseg.report.segments import meta_console, meta_json, meta_table, write_segments
from costseg.report.tables import (
    PAPER_COLUMNS,
    PAPER_ROIS,
    compare_with_paper,
    console_table,
    format_value,
    markdown_table,
    paper_table,
)
from costseg.report.tensorboard import (
    log_evaluation,
    log_masks,
    log_png,
    log_table,
    summary_writer,
)
from costseg.report.uncertainty import uncertainty_strip
from costseg.rules import DEFER_COLUMN

SUMMARY_COLUMNS = (*PAPER_COLUMNS, *ERROR_COLUMNS)
DEFER_SUMMARY = (DEFER_COLUMN, "coverage", "handled_recall", *DEFER_RULE_RATES)
"""The console's columns of deferral, where a named rule defers (table.md and the files hold
every column)."""


def write_evaluation(results: EvalResults, early: EarlyFigures) -> None:
    """Write the named rules' results, then each sweep's, into ``results.output_dir``.

    ``early``: the figures started while the images were evaluated, and the workers that draw
    the others."""
    from costseg.report.calibration import calibration_rows, write_calibration
    from costseg.report.sweep import write_sweeps

    out = results.output_dir
    named = results.named
    rows = named.rows(results.class_ids)
    headline = [r for r in rows if r["roi"] in PAPER_ROIS]
    print(f"probabilities: {results.probabilities}")
    if loss := training_loss(results.source):
        print(f"training loss: {loss}")
    instances = INSTANCE_COLUMNS[:2] if named.instances else ()
    deferral = DEFER_SUMMARY if named.group.defers else ()
    print(console_table(headline, (*SUMMARY_COLUMNS, *deferral, *instances)))
    print("mIoU: " + ", ".join(f"{n} {100 * v:.2f}" for n, v in _miou(named).items()))
    if meta := meta_console(results.segments):
        print(meta)
    tables = _tables(headline, named, _probability_note(results)) + _risk_coverage_table(results)
    if meta := meta_table(results.segments):
        tables += "\n\n" + meta + "\n"
    if unknown := anomaly_table(results.extra.get("anomalies")):
        tables += "\n\n" + unknown + "\n"
    write_text(out / "table.md", tables)
    write_csv(out / "results.csv", rows)
    write_json(out / "results.json", _json(results, rows))
    with summary_writer(out) as writer:
        log_table(writer, "evaluation/table", tables)
        log_evaluation(writer, results, rows)
        log_anomalies(writer, results.extra.get("anomalies"))
        if calibration := calibration_rows(results.extra.get("ece", {})):
            log_table(writer, "evaluation/calibration", markdown_table(calibration))
        shown = mask_names([g.group for g in results.groups])
        for i, ex in enumerate(results.examples):
            log_masks(
                writer,
                f"evaluation/masks/{i}",
                ex.image.permute(1, 2, 0).numpy(),
                ex.label.numpy(),
                {n: ex.preds[k].numpy() for k, n in enumerate(shown)},
            )
            if ex.uncertainty:
                maps = {k: v.float().numpy() for k, v in ex.uncertainty.items()}
                strip = uncertainty_strip(maps, len(CLASS_NAMES))
                writer.add_image(f"evaluation/uncertainty/{i}", strip, dataformats="HWC")
        jobs = [] if early.plan_started else plan_figures(named.group, results.roi)
        if not early.examples_started:
            jobs.append(("evaluation", example_figures(shown, results.examples, results.subject)))
        jobs += write_sweeps(results) + _figures(results) + write_calibration(results)
        jobs += write_segments(results, writer) + anomaly_jobs(
            results.extra.get("anomalies"), results.subject
        )
        _draw_and_log(writer, jobs, early.drawing)
    if results.options.get("explorer"):
        from costseg.report.explorer_points import write_evaluation_explorer

        write_evaluation_explorer(results)
    print(f"results written to {out}")


def _draw_and_log(writer: SummaryWriter, jobs: list[tuple[str, Job]], drawing: Drawing) -> None:
    """Draw each ``(prefix, job)`` after those already submitted to ``drawing``, then log every
    figure to TensorBoard as ``prefix/<tag>`` in the jobs' order."""
    for prefix, drawn_job in jobs:
        drawing.submit(prefix, drawn_job)
    for prefix, figures in drawing.finish():
        for tag, shape in figures:
            log_png(writer, f"{prefix}/{tag}", figure_path(drawing.folder, tag).read_bytes(), shape)


def _probability_note(results: EvalResults) -> str:
    from costseg.report.calibration import calibration_line, calibration_rows

    rows = calibration_rows(results.extra.get("ece", {}))
    note = results.probabilities + (f"; {calibration_line(rows)}" if rows else "")
    if loss := training_loss(results.source):
        note += f"; the network was trained with {loss}"
    return note + (f". {results.extra['instances']}" if "instances" in results.extra else "")


def training_loss(source: dict[str, Any]) -> str | None:
    """The loss a costseg checkpoint records (docs/definitions.md §16) as ``Name(arg=value)``,
    or None.

    >>> training_loss({"hparams": {"loss": {"class_path": "m.FocalLoss",
    ...                                     "init_args": {"gamma": 2.0}}}})
    'FocalLoss(gamma=2.0)'
    """
    entry = (source.get("hparams") or {}).get("loss")
    if not entry:
        return None
    args = ", ".join(f"{k}={v}" for k, v in entry.get("init_args", {}).items() if v is not None)
    return f"{entry['class_path'].rpartition('.')[2]}({args})"


def _miou(result: GroupResult) -> dict[str, float]:
    return {n: result.pixels["miou"][k].item() for k, n in enumerate(result.group.names)}


def _tables(headline: list[dict], named: GroupResult, probabilities: str) -> str:
    return "\n\n".join(
        [
            "# Precision and recall per cost matrix (RoI 1 = street, 2 = sidewalk)",
            f"Probabilities: {probabilities}.",
            paper_table(headline),
            _miou_table(named),
            "## Next to the paper (Cityscapes val, DeepLabv3+ Xception)",
            compare_with_paper(headline) + "\n",
        ]
    )


def _miou_table(named: GroupResult) -> str:
    """The mIoU of each named rule; where one defers, its defer cost and the share of the
    image's pixels it deferred (a deferred pixel is a false negative of its class in IoU)."""
    if not named.group.defers:
        miou = "\n".join(f"| {n} | {100 * v:.2f} |" for n, v in _miou(named).items())
        return f"## mIoU (19 classes)\n\n| matrix | mIoU |\n|---|---|\n{miou}"
    lines = [
        f"| {rule.name} | {format_value(rule.defer_cost)} | {100 * miou:.2f} | "
        f"{format_value(named.pixels['deferred_rate'][k, 0].item(), percent=True)} |"
        for k, (rule, miou) in enumerate(zip(named.group.rules, _miou(named).values(), strict=True))
    ]
    return (
        "## mIoU (19 classes; a deferred pixel is a false negative of its class)\n\n"
        "| matrix | defer | mIoU | deferred (whole image) |\n|---|---|---|---|\n" + "\n".join(lines)
    )


def _json(results: EvalResults, rows: list[dict]) -> dict:
    named = results.named
    pixels, names = named.pixels, named.group.names
    return {
        "options": results.options,
        "source": results.source,
        "probabilities": results.probabilities,
        "images": results.num_images,
        "rois": list(ROI_NAMES),
        "rows": rows,
        "miou": _miou(named),
        "iou": {
            n: dict(zip(CLASS_NAMES, pixels["iou"][k].tolist(), strict=False))
            for k, n in enumerate(names)
        },
        "confusion_matrix": {
            "layout": "[rule][true class][predicted class], whole image, pixels"
            + (" not deferred" if named.group.defers else ""),
            **{n: pixels["confmat"][k, 0].tolist() for k, n in enumerate(names)},
        },
        **_deferral_json(named),
        **risk_coverage_json(results),
        "instances": results.extra.get("instances"),
        "scaling": results.extra.get("scaling"),
        "meta": meta_json(results.segments),
        "anomalies": anomaly_json(results.extra.get("anomalies")),
        **_calibration(results),
    }


def _deferral_json(named: GroupResult) -> dict:
    """Where a named rule defers: each rule's defer cost (null: it never defers) and its
    deferred pixels per true class."""
    if not named.group.defers:
        return {}
    names = named.group.names
    return {
        "defer": {r.name: r.defer_cost for r in named.group.rules},
        "deferred_pixels": {
            "layout": "[rule][true class], whole image, pixels deferred",
            **{n: named.pixels["deferred"][k, 0].tolist() for k, n in enumerate(names)},
        },
    }


def _risk_coverage_table(results: EvalResults) -> str:
    table = risk_coverage_table(results)
    return f"\n{table}\n" if table else ""


def _calibration(results: EvalResults) -> dict:
    from costseg.report.calibration import calibration_record, calibration_rows

    return calibration_record(calibration_rows(results.extra.get("ece", {})))


def _figures(results: EvalResults) -> list[tuple[str, Job]]:
    """The named rules' figures from their results, undrawn, as jobs: figures of one kind
    are one figure redrawn."""
    named = results.named
    names, segments, instances = named.group.names, named.segments, named.instances
    grids = []
    for kind, key in (("FP", "fp_map"), ("FN", "fn_map")):
        maps = {
            (n, CLASS_NAMES[cls]): segments[key][k, c]
            for k, n in enumerate(names)
            for c, cls in enumerate(results.class_ids)
        }
        grids.append((f"{kind.lower()}_segments", maps, kind))
    if instances and instances["missed_map"].shape[-1] > 0:
        maps = {
            (n, CLASS_NAMES[cls]): instances["missed_map"][k, c]
            for k, n in enumerate(names)
            for c, cls in enumerate(instances["classes"].tolist())
        }
        grids.append(("missed_instances", maps, "missed instances"))
    return [("evaluation", job(heatmap_grid_figures, grids, results.subject))]
