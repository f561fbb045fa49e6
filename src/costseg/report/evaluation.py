"""Everything ``evaluate.py`` writes: each analysis's result writes its own files and returns
its share of the shared outputs (:mod:`costseg.report.sections`), which are joined here into
``table.md``, ``results.json``, the terminal, TensorBoard and the figures."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

from torch.utils.tensorboard import SummaryWriter

from costseg.classes import ROI_NAMES
from costseg.report.drawing import Drawing, Job, figure_path
from costseg.report.early_figures import EarlyFigures, plan_figures
from costseg.report.files import write_json, write_text
from costseg.report.headline import training_loss
from costseg.report.results import EvalResults
from costseg.report.sections import Curve, merge
from costseg.report.tensorboard import (
    STEPS,
    close_writer,
    log_png,
    log_scalars,
    log_table,
    summary_writer,
)


def write_evaluation(results: EvalResults, early: EarlyFigures) -> None:
    """Write every analysis's outputs into ``results.output_dir``.

    ``early``: the figures started while the images were evaluated, and the workers that draw
    the others."""
    out = results.output_dir
    print(f"probabilities: {results.probabilities}")
    if loss := training_loss(results.source):
        print(f"training loss: {loss}")
    shared = merge(r.write(results) for r in results.analyses)
    for line in shared.console:
        print(line)
    write_text(out / "table.md", shared.table)
    write_json(out / "results.json", _json(results) | shared.json)
    with summary_writer(out) as writer:
        log_table(writer, "evaluation/table", shared.table)
        for tag, markdown in shared.tables.items():
            log_table(writer, tag, markdown)
        _log_curves(writer, out, shared.curves)
        for log in shared.logs:
            log(writer)
        jobs = [] if early.plan_started else plan_figures(results.named.group, results.roi)
        _draw_and_log(writer, jobs + shared.jobs, early.drawing)
    print(f"results written to {out}")


def _json(results: EvalResults) -> dict:
    """What results.json says of every evaluation (each analysis adds its keys)."""
    return {
        "options": results.options_record,
        "source": results.source,
        "probabilities": results.probabilities,
        "images": results.num_images,
        "rois": list(ROI_NAMES),
        **dict.fromkeys(results.null_keys),
    }


def _log_curves(writer: SummaryWriter, out: Path, curves: Sequence[Curve]) -> None:
    """Each curve's values along its steps; a class's curves in its own run
    (``<out>/tensorboard/<class>``), overlaid in one card per metric."""
    if not curves:
        return
    log_table(writer, "evaluation/steps", STEPS)
    runs: dict[str, SummaryWriter] = {}
    for tag, run, steps, values in curves:
        if run is not None and run not in runs:
            runs[run] = SummaryWriter(str(out / "tensorboard" / run))
        target = writer if run is None else runs[run]
        for step, value in zip(steps, values, strict=True):
            log_scalars(target, {tag: value}, step)
    for run_writer in runs.values():
        close_writer(run_writer)


def _draw_and_log(writer: SummaryWriter, jobs: list[tuple[str, Job]], drawing: Drawing) -> None:
    """Draw each ``(prefix, job)`` after those already submitted to ``drawing``, then log every
    figure to TensorBoard as ``prefix/<tag>`` in the jobs' order."""
    for prefix, drawn_job in jobs:
        drawing.submit(prefix, drawn_job)
    for prefix, figures in drawing.finish():
        for tag, shape in figures:
            log_png(writer, f"{prefix}/{tag}", figure_path(drawing.folder, tag).read_bytes(), shape)
