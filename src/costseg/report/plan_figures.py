"""The figures known before the first image: the named rules' cost matrices and the RoI map.

:func:`start_plan_figures` draws them on a forked process while the images are evaluated.
Importing this module imports neither matplotlib nor TensorBoard (the batches import what they
draw with when they are first drawn), so the first image waits for neither.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING

import torch

from costseg.classes import CLASS_NAMES
from costseg.report.drawing import Batch, Drawing
from costseg.rules import RuleGroup

if TYPE_CHECKING:
    from matplotlib.figure import Figure


def start_plan_figures(output_dir: Path, group: RuleGroup, roi: torch.Tensor | None) -> Drawing:
    """Start drawing :func:`plan_figures` into ``output_dir/figures`` on a forked process; pass
    the result to :func:`costseg.report.evaluation.write_evaluation`."""
    return Drawing(plan_figures(group, roi), output_dir / "figures", workers=1)


def plan_figures(group: RuleGroup, roi: torch.Tensor | None) -> list[tuple[str, Batch]]:
    """``(TensorBoard prefix, batch)`` of the cost matrices of ``group`` and of the RoI map."""
    costs = [(f"cost_{r.name}", r.cost, r.name) for r in group.rules if r.cost is not None]
    batches = [("evaluation", _cost_matrices(costs))]
    return batches + ([] if roi is None else [("evaluation", _roi_map(roi.cpu()))])


def _cost_matrices(costs: list) -> Iterator[tuple[str, Figure]]:
    from costseg.report.cost_matrix import cost_matrix_figures

    yield from cost_matrix_figures(costs, CLASS_NAMES)


def _roi_map(roi: torch.Tensor) -> Iterator[tuple[str, Figure]]:
    from costseg.report.priors import plot_roi_map

    yield "roi_map", plot_roi_map(roi)
