"""The one loop of an evaluation: the held-out images once → every analysis fits → the reported
images once → scores → probabilities → every rule group's label maps → every analysis.

The loop names no analysis and no rule family: the analyses the options ask for come from
:data:`costseg.evaluation.analyses.ANALYSES`, and each rule group decides on the probabilities
of its temperature (the main ones, or the raw logits' at ``T``).
"""

from __future__ import annotations

from dataclasses import asdict
from typing import TYPE_CHECKING

import torch

from costseg.calibration.scaling import Scaling
from costseg.evaluation.analyses import Analysis, Context, analysis_class, null_keys, wanted
from costseg.evaluation.held_out import HeldOut
from costseg.evaluation.plan import EvalPlan
from costseg.evaluation.processes import rank
from costseg.networks.sources import batches
from costseg.report.results import EvalResults

if TYPE_CHECKING:
    from costseg.report.early_figures import EarlyFigures


def run(plan: EvalPlan, early: EarlyFigures | None = None) -> EvalResults:
    """Fit every analysis on the held-out images, then pass over the reported ones once;
    ``early`` starts drawing figures while the images are evaluated."""
    context = Context(plan, Scaling(), *held_out_images(plan), early=early)
    entries = wanted(plan.options)
    analyses = [analysis_class(e)(context) for e in entries]
    for analysis in analyses:
        analysis.fit()
    for analysis in analyses:
        analysis.start()
    with torch.inference_mode():
        seen_so_far = 0
        for batch in _reported_batches(plan, analyses):
            positions = plan.positions[seen_so_far : seen_so_far + len(batch.labels)]
            seen = context.see(batch, positions)
            for analysis in analyses:
                analysis.process(seen)
            seen_so_far += len(positions)
    for analysis in analyses:
        analysis.gather()
    ran = {e: a.result() for e, a in zip(entries, analyses, strict=True)}
    return EvalResults(
        output_dir=plan.output_dir,
        options=asdict(plan.options),
        source=plan.source.description,
        probabilities=_describe_probabilities(plan, context.scaling),
        class_ids=plan.class_ids,
        roi=plan.priors.roi_map(),
        num_images=plan.num_reported,
        analyses=[r for r in ran.values() if r is not None],
        null_keys=null_keys(ran),
    )


def held_out_images(plan: EvalPlan) -> tuple[HeldOut | None, HeldOut | None]:
    """The calibration images and the meta models' images, each through the network once
    (the same object when they are the same images; kept for every shift of the plan)."""
    if "images" not in plan.held_out:
        segments = plan.meta_images is not None
        calibration = None
        if plan.calibration is not None:
            dataset, indices = plan.calibration
            shared = plan.meta_images is plan.calibration
            calibration = HeldOut(plan, dataset, indices, entropy=shared)
        meta = calibration if plan.meta_images is plan.calibration else None
        if segments and meta is None:
            meta = HeldOut(plan, *plan.meta_images, entropy=True)
        plan.held_out["images"] = (calibration, meta)
    return plan.held_out["images"]


def close_held_out(plan: EvalPlan) -> None:
    """Remove the held-out scores kept on disk (the evaluation, with all its shifts, ended)."""
    for held in plan.held_out.pop("images", ()):
        if held is not None:
            held.close()


def _reported_batches(plan: EvalPlan, analyses: list[Analysis]):
    """The reported images, scored; the expected entropy of a source of several runs for the
    first images only, unless an analysis wants it for every image."""
    entropy = None if any(a.every_entropy for a in analyses) else plan.options.num_examples
    desc = "evaluate" if plan.options.progress and rank() == 0 else None
    return batches(
        plan.source, plan.dataset, plan.indices, plan.batch_size, plan.device, plan.num_workers,
        desc, entropy,
    )  # fmt: skip


def _describe_probabilities(plan: EvalPlan, scaling: Scaling) -> str:
    base = plan.source.probabilities  # saved ones, Monte-Carlo dropout, or None: the softmax
    if scaling.kind == "none" and base:
        text = f"{base}, no scaling"
    else:
        text = (f"{base}; " if base else "") + scaling.describe()
    text += "; rounded to float16 as saved" if plan.options.save_probs else ""
    if len(plan.shifts) == 1:
        text += f"; the images seen through {plan.shifts[0]} (definitions §17)"
    return text
