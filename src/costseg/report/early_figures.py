"""Figures drawn on forked processes while the images are evaluated.

After the first batch (the first image waits for nothing): the named rules' cost matrices and
the RoI map, known from the plan; once the examples are complete, their mask figures. Importing
this module imports neither matplotlib nor TensorBoard: each batch imports what it draws with
when it is first drawn.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import torch

from costseg.classes import CLASS_NAMES
from costseg.report.drawing import Batch, Drawing, Drawn
from costseg.report.results import Example
from costseg.rules import RuleGroup

if TYPE_CHECKING:
    from matplotlib.figure import Figure


class EarlyFigures:
    """Pass :meth:`after_batch` to :func:`costseg.evaluation.run.run`, then this object to
    :func:`costseg.report.evaluation.write_evaluation`, which draws the rest.

    Args:
        output_dir: the evaluation's folder (figures go to its ``figures/``).
        group: the named rules.
        roi: (H, W) RoI map, or None.
        num_examples: images of the mask figures.
    """

    def __init__(
        self, output_dir: Path, group: RuleGroup, roi: torch.Tensor | None, num_examples: int
    ) -> None:
        self.folder, self.group, self.roi = output_dir / "figures", group, roi
        self.num_examples, self.drawings = num_examples, []
        self.plan_started = self.examples_started = False

    def after_batch(self, examples: list[Example]) -> None:
        """Start what can be drawn now: the plan's figures, then the examples' once complete."""
        if not self.plan_started:
            self.drawings.append(Drawing(plan_figures(self.group, self.roi), self.folder, 1))
            self.plan_started = True
        if not self.examples_started and len(examples) >= self.num_examples > 0:
            batch = ("evaluation", example_figures(self.group.names, examples))
            self.drawings.append(Drawing([batch], self.folder, 1))
            self.examples_started = True

    def finish(self) -> list[tuple[str, Drawn]]:
        """``(prefix, tags and image shapes)`` of every batch started, once drawn."""
        return [drawn for drawing in self.drawings for drawn in drawing.finish()]

    def cancel(self) -> None:
        """Stop drawing (the evaluation failed)."""
        for drawing in self.drawings:
            drawing.cancel()


def plan_figures(group: RuleGroup, roi: torch.Tensor | None) -> list[tuple[str, Batch]]:
    """``(TensorBoard prefix, batch)`` of the cost matrices of ``group`` and of the RoI map."""
    costs = [(f"cost_{r.name}", r.cost, r.name) for r in group.rules if r.cost is not None]
    batches = [("evaluation", _cost_matrices(costs))]
    return batches + ([] if roi is None else [("evaluation", _roi_map(roi.cpu()))])


def example_figures(names: Sequence[str], examples: list[Example]) -> Iterator[tuple[str, Figure]]:
    """The mask figure of each example: image, ground truth, each named rule's labels and the
    uncertainty maps, each titled with its scale (docs/definitions.md §13)."""
    from costseg.report.figures import mask_figures
    from costseg.report.uncertainty import uncertainty_tiles

    yield from mask_figures(
        (
            f"masks_{i}",
            ex.image.permute(1, 2, 0).numpy(),
            ex.label.numpy(),
            {n: ex.preds[k].numpy() for k, n in enumerate(names)},
            {
                t.scale: t.rgb
                for t in uncertainty_tiles(
                    {k: v.float().numpy() for k, v in ex.uncertainty.items()}, len(CLASS_NAMES)
                )
            },
        )
        for i, ex in enumerate(examples)
    )


def _cost_matrices(costs: list) -> Iterator[tuple[str, Figure]]:
    from costseg.report.cost_matrix import cost_matrix_figures

    yield from cost_matrix_figures(costs, CLASS_NAMES)


def _roi_map(roi: torch.Tensor) -> Iterator[tuple[str, Figure]]:
    from costseg.report.priors import plot_roi_map

    yield "roi_map", plot_roi_map(roi)
