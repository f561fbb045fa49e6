"""The prior-adapted path of ``--alpha_sweep``: one rule on ``p / π_α``, ``π_α = (1 - α) + α π``,
for α from 0 (Bayes) to 1 (maximum likelihood), decided as one group (docs/definitions.md §1).

>>> alpha_group(0.5).names
['robotistic@alpha=0.00', 'robotistic@alpha=0.50', 'robotistic@alpha=1.00']
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch

from costseg.classes import CLASS_NAMES
from costseg.decision import decide
from costseg.rules.base import RuleGroup, adapted_priors, given_priors, plain_rules
from costseg.rules.named import parse_rules
from costseg.values import steps_per_unit


@dataclass(frozen=True)
class PriorAdapted:
    """``probs, priors → (B, K, H, W)``: the rule of ``cost`` on ``p / π_α`` for each α."""

    cost: torch.Tensor | None
    alphas: tuple[float, ...]

    def __call__(self, probs: torch.Tensor, priors: torch.Tensor | None, roi=None) -> torch.Tensor:
        priors = given_priors(priors, "the α sweep")
        return torch.stack(
            [decide(probs, self.cost, adapted_priors(priors, a)) for a in self.alphas], 1
        )


def alpha_grid(step: float) -> list[float]:
    """α = 0, step, …, 1.

    >>> alpha_grid(0.25)
    [0.0, 0.25, 0.5, 0.75, 1.0]
    """
    n = steps_per_unit(step, "alpha step")
    return [i / n for i in range(n + 1)]


def alpha_group(
    step: float, cost_name: str | None = None, class_names: Sequence[str] = CLASS_NAMES
) -> RuleGroup:
    """The prior-adapted rule on ``p / π_α`` for α = 0, step, …, 1 (0 = Bayes, 1 = ML)."""
    base = (
        plain_rules(parse_rules([cost_name], class_names), "--alpha_cost")[0] if cost_name else None
    )
    if base is not None and base.priors_alpha:
        raise ValueError("--alpha_cost must be a cost matrix, not 'ml'")
    if base is not None and base.defers:
        raise ValueError(f"--alpha_cost {cost_name} has a defer row: the α sweep takes N x N costs")
    cost, label = (base.cost, base.name) if base else (None, "robotistic")
    alphas = alpha_grid(step)
    return RuleGroup(
        "alpha",
        [f"{label}@alpha={a:.2f}" for a in alphas],
        PriorAdapted(cost, tuple(alphas)),
        [{"prior_alpha": a} for a in alphas],
        needs_priors=True,
        candidates=True,
        output="alpha_sweep",
        line=tuple(alphas),
        axis="α (0 = Bayes, 1 = maximum likelihood)",
        note=f"{label} on p/π_α, π_α = (1-α) + απ",
    )
