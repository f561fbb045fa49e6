"""The value-space triangle of ``--sweep``: every mixture ``α·A + β·B + γ·C`` of three vertex
cost matrices on a barycentric grid, decided as one group (docs/definitions.md §2).

>>> group = grid_group(["robotistic", "altruistic", "egoistic"], 0.5)
>>> group.names[:2], group.columns[1]
(['w=1.00/0.00/0.00', 'w=0.50/0.50/0.00'], {'alpha': 0.5, 'beta': 0.5, 'gamma': 0.0})
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch

from costseg.classes import CLASS_NAMES
from costseg.costs import barycentric_grid, cost_or_symmetric, rescale
from costseg.decision import decide_mixtures
from costseg.rules.base import RuleGroup, needs_priors, plain_rules
from costseg.rules.named import parse_rules

WEIGHT_COLUMNS = ("alpha", "beta", "gamma")
"""The result columns of a grid point's barycentric weights."""


@dataclass(frozen=True)
class Mixtures:
    """``probs, priors → (B, K, H, W)`` for K mixtures of the vertices (a class, not a closure:
    groups travel to DDP worker processes, so they must pickle)."""

    vertices: torch.Tensor
    weights: torch.Tensor

    def __call__(self, probs: torch.Tensor, priors: torch.Tensor | None, roi=None) -> torch.Tensor:
        return decide_mixtures(probs, self.vertices, self.weights)


def vertex_matrices(
    names: Sequence[str], scaling: str = "none", class_names: Sequence[str] = CLASS_NAMES
) -> torch.Tensor:
    """The three vertex cost matrices (3, N, N), optionally rescaled to unit mean cost."""
    if len(names) != 3:
        raise ValueError(f"a sweep needs exactly 3 vertex costs, got {len(names)}: {list(names)}")
    if scaling not in ("none", "mean"):
        raise ValueError(f"vertex scaling must be 'none' or 'mean', got {scaling!r}")
    rules = plain_rules(parse_rules(names, class_names), "a vertex of the triangle")
    if needs_priors(rules):
        raise ValueError("'ml' uses pixel-wise priors and is no matrix: it cannot be a vertex")
    if any(r.defers for r in rules):
        raise ValueError("a vertex of the triangle cannot have a defer row (it is an N x N cost)")
    vertices = torch.stack([cost_or_symmetric(r.cost, len(class_names)) for r in rules])
    return rescale(vertices) if scaling == "mean" else vertices


def point_name(weights: Sequence[float]) -> str:
    """``w=0.70/0.20/0.10`` for the grid point (α, β, γ)."""
    return "w=" + "/".join(f"{w:.2f}" for w in weights)


def grid_group(
    vertex_names: Sequence[str],
    step: float,
    scaling: str = "none",
    class_names: Sequence[str] = CLASS_NAMES,
) -> RuleGroup:
    """Every point of the barycentric grid of ``step`` as one group, by mixing vertex costs."""
    vertices = vertex_matrices(vertex_names, scaling, class_names)
    weights = barycentric_grid(step)
    return RuleGroup(
        "grid",
        [point_name(w) for w in weights.tolist()],
        Mixtures(vertices, weights),
        [dict(zip(WEIGHT_COLUMNS, w, strict=True)) for w in weights.tolist()],
        candidates=True,
        output="sweep",
        vertices=vertices,
        weights=weights,
        corners=tuple(vertex_names),
        note=f"vertices: {', '.join(vertex_names)}; vertex scaling: {scaling}",
    )
