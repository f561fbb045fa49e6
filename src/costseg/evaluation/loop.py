"""The one loop of an evaluation: the held-out images once → every analysis fits → the reported
images once → scores → probabilities → every rule group's label maps → every analysis.

The loop names no analysis and no rule family: the plan's analyses are entries of
:data:`costseg.evaluation.analyses.ANALYSES`, and each rule group decides on the probabilities
of its temperature (the main ones, or the raw logits' at ``T``).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import torch

from costseg.calibration.scaling import Scaling
from costseg.evaluation.analyses import Analysis, Context, analysis_class, fit_order, null_keys
from costseg.evaluation.held_out import HeldOut
from costseg.evaluation.plan import EvalPlan
from costseg.evaluation.processes import rank
from costseg.networks.sources import batches
from costseg.report.results import EvalResults

if TYPE_CHECKING:
    from costseg.report.early_figures import EarlyFigures


def run(
    plan: EvalPlan,
    held_out: tuple[HeldOut | None, HeldOut | None] = (None, None),
    early: EarlyFigures | None = None,
) -> EvalResults:
    """Fit every analysis on the held-out images (the calibration images, the meta models'),
    apply what each fit provides, freeze the rule groups, then pass over the reported images
    once; ``early`` starts drawing figures while the images are evaluated."""
    context = Context(plan, Scaling(), *held_out, early=early)
    analyses = {entry: analysis_class(entry)(given, context) for entry, given in plan.analyses}
    for entry in fit_order(list(analyses)):
        context.apply(analyses[entry].fit())
    context.freeze()
    for analysis in analyses.values():
        analysis.start()
    with torch.inference_mode():
        seen_so_far = 0
        for batch in _reported_batches(plan, list(analyses.values())):
            positions = plan.positions[seen_so_far : seen_so_far + len(batch.labels)]
            seen = context.see(batch, positions)
            for analysis in analyses.values():
                analysis.process(seen)
            seen_so_far += len(positions)
    for analysis in analyses.values():
        analysis.gather()
    ran = {e: a.result() for e, a in analyses.items()}
    return EvalResults(
        output_dir=plan.output_dir,
        options_record=plan.record,
        source=_describe_source(plan),
        probabilities=_describe_probabilities(plan, context.scaling),
        class_ids=plan.class_ids,
        rois=plan.rois,
        roi=plan.priors.roi_map(),
        num_images=plan.num_reported,
        analyses=[r for r in ran.values() if r is not None],
        null_keys=null_keys(ran),
        shifts=[str(s) for s in plan.shifts],
    )


def _reported_batches(plan: EvalPlan, analyses: list[Analysis]):
    """The reported images, scored; the expected entropy of a source of several runs for the
    first images only, unless an analysis wants it for every image."""
    entropy = None if any(a.every_entropy for a in analyses) else plan.num_examples
    desc = "evaluate" if plan.progress and rank() == 0 else None
    return batches(
        plan.source, plan.dataset, plan.indices, plan.batch_size, plan.device, plan.num_workers,
        desc, entropy,
    )  # fmt: skip


def _describe_source(plan: EvalPlan) -> dict:
    """The source's description of the plan, with what scoring met (the sizes resized)."""
    resized = plan.source.resized_to_labels
    return plan.description | ({"resized_to_labels": list(resized)} if resized else {})


def _describe_probabilities(plan: EvalPlan, scaling: Scaling) -> str:
    base = plan.source.probabilities  # saved ones, Monte-Carlo dropout, or None: the softmax
    if scaling.kind == "none" and base:
        text = f"{base}, no scaling"
    else:
        text = (f"{base}; " if base else "") + scaling.describe()
    text += "; rounded to float16 as saved" if plan.round_probs else ""
    if len(plan.shifts) == 1:
        text += f"; the images seen through {plan.shifts[0]} (definitions §17)"
    return text
