"""Figures drawn while the images are evaluated, and the workers that draw every figure.

After the first batch (the first image waits for nothing): the named rules' cost matrices and
the RoI map, known from the plan; once the examples are complete, their mask figures. The
workers (:class:`costseg.report.drawing.Drawing`) start with this object and draw the report's
other figures afterwards. Importing this module imports neither matplotlib nor TensorBoard.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path

import torch

from costseg.classes import CLASS_NAMES, ROI_NAMES
from costseg.decision.regions import distinct
from costseg.report.drawing import Drawing, Job, job
from costseg.report.results import Example
from costseg.rules import Rule, RuleGroup, masked_groups, named_group


class EarlyFigures:
    """Pass :meth:`after_batch` to :func:`costseg.evaluation.run.run`, then this object to
    :func:`costseg.report.evaluation.write_evaluation`, which submits the rest to
    :attr:`drawing`.

    Args:
        output_dir: the evaluation's folder (figures go to its ``figures/``).
        groups: the evaluation's rule groups (the named rules' cost matrices are drawn, the
            rules of :func:`~costseg.rules.masked_groups` fill the mask figures).
        roi: (H, W) RoI map, or None.
        num_examples: images of the mask figures.
        subject: the network and shift, for the figures' titles
            (:func:`costseg.report.results.figure_subject`).
    """

    def __init__(
        self,
        output_dir: Path,
        groups: Sequence[RuleGroup],
        roi: torch.Tensor | None,
        num_examples: int,
        subject: str = "",
    ) -> None:
        self.drawing = Drawing(output_dir / "figures", len(os.sched_getaffinity(0)))
        self.group, self.roi, self.num_examples = named_group(groups), roi, num_examples
        self.subject = subject
        self.plan_started = self.examples_started = False

    def after_batch(self, examples: list[Example], groups: Sequence[RuleGroup]) -> None:
        """Start what can be drawn now: the plan's figures, then the examples' once complete
        (their label maps those of ``groups``' :func:`mask_names`)."""
        if not self.plan_started:
            for prefix, plan_job in plan_figures(self.group, self.roi):
                self.drawing.submit(prefix, plan_job)
            self.plan_started = True
        if not self.examples_started and len(examples) >= self.num_examples > 0:
            self.drawing.submit(
                "evaluation", example_figures(mask_names(groups), examples, self.subject)
            )
            self.examples_started = True

    def cancel(self) -> None:
        """Stop drawing (the evaluation failed)."""
        self.drawing.cancel()


def plan_figures(group: RuleGroup, roi: torch.Tensor | None) -> list[tuple[str, Job]]:
    """``(TensorBoard prefix, job)`` of the cost matrices of ``group`` and of the RoI map."""
    from costseg.report.cost_matrix import cost_matrix_figures
    from costseg.report.priors import roi_map_figures

    costs = [shown for r in group.rules if r.cost is not None for shown in shown_matrices(r)]
    jobs = [("evaluation", job(cost_matrix_figures, costs, CLASS_NAMES))]
    return jobs + (
        [] if roi is None else [("evaluation", job(roi_map_figures, roi.to(torch.uint8)))]
    )


def shown_matrices(rule: Rule) -> list[tuple[str, torch.Tensor, str]]:
    """``(tag, matrix, title)`` of each matrix of ``rule``: its one matrix, or each distinct
    matrix of a regional rule with the RoIs that use it (docs/definitions.md §21).

    >>> from costseg.costs import symmetric_cost
    >>> stack = torch.stack([symmetric_cost(2)] * 5)
    >>> stack[1] *= 2
    >>> [(tag, title) for tag, _, title in shown_matrices(Rule("s", stack))]
    [('cost_s', 's: default (RoIs 2, 3, 4)'), ('cost_s_roi1', 's: RoI 1 (street)')]
    """
    if not rule.regional:
        return [(f"cost_{rule.name}", rule.cost, rule.name)]
    matrices, index = distinct(rule.cost)
    shown = []
    for d, matrix in enumerate(matrices):
        rois = [r for r in range(len(index)) if index[r] == d]
        ids, names = ", ".join(str(r) for r in rois if r), ", ".join(ROI_NAMES[r] for r in rois)
        if 0 in rois:
            tag, where = f"cost_{rule.name}", "default" + (f" (RoIs {ids})" if ids else "")
        else:
            tag, where = (
                f"cost_{rule.name}_roi{rois[0]}",
                f"RoI{'s' * (len(rois) > 1)} {ids} ({names})",
            )
        shown.append((tag, matrix, f"{rule.name}: {where}"))
    return shown


def mask_names(groups: Sequence[RuleGroup]) -> list[str]:
    """The rules of the mask figures, in the order of the examples' label maps."""
    return [name for g in masked_groups(groups) for name in g.names]


def example_figures(names: Sequence[str], examples: list[Example], subject: str = "") -> Job:
    """The mask figure of each example: image, ground truth, each shown rule's labels and the
    uncertainty maps, each titled with its scale (docs/definitions.md §13); ``subject`` (the
    network and shift) above them."""
    from costseg.report.figures import example_mask_figures

    return job(
        example_mask_figures,
        list(names),
        [
            (
                ex.image.permute(1, 2, 0),
                ex.label.to(torch.uint8),  # train ids and 255: ignored or deferred
                ex.preds.to(torch.uint8),
                ex.uncertainty,  # float16, as kept
            )
            for ex in examples
        ],
        subject,
    )
