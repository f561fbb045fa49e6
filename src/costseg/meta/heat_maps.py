"""The heat maps behind the segment features (docs/definitions.md §15), per pixel, in float32.

* ``E``: the normalised entropy ``Σ_k p_k log(p_k + ε) / log(1/N)``, ε the float32 machine
  epsilon (MetaSeg's), in [0, 1];
* ``D``: ``1 − p_(1) + p_(2)``, one minus the margin of the two largest probabilities;
* ``R``: the rule's cost margin, (second-lowest − lowest expected cost) / (largest off-diagonal
  cost), over the rule's decisions (a defer row is one more); computed on ``p / π_α`` for a rule
  with priors, as the rule decides;
* ``MI``: the mutual information of the runs behind the probabilities (Monte-Carlo dropout's
  passes, an ensemble's members, docs/definitions.md §13), where the source has several.

>>> p = torch.tensor([[[[0.7]], [[0.2]], [[0.1]]]])   # (B, N, H, W): one pixel, three classes
>>> maps = heat_maps(p, Rule("robotistic", None))
>>> {k: round(float(v), 4) for k, v in maps.items()}
{'E': 0.7298, 'D': 0.5, 'R': 0.5}
"""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import Tensor

from costseg.costs import cost_or_symmetric, off_diagonal
from costseg.decision import expected_costs
from costseg.networks.uncertainty import entropy
from costseg.rules.base import Rule, adapted_priors, given_priors

EPSILON = float(np.finfo(np.float32).eps)


def heat_maps(
    probs: Tensor,
    rule: Rule | None = None,
    priors: Tensor | None = None,
    expected_entropy: Tensor | None = None,
    roi: Tensor | None = None,
) -> dict[str, Tensor]:
    """(B, H, W) float32 maps E, D, and R for ``rule``, MI with ``expected_entropy``.

    Args:
        probs: (B, N, H, W) probabilities.
        rule: the rule whose cost margin R is wanted (None: no R).
        priors: (N, H, W) pixel-wise priors, for a rule that divides by them.
        expected_entropy: (B, H, W) mean entropy of the runs (None: one run, no MI).
        roi: (H, W) RoI ids, for a regional rule (docs/definitions.md §21).
    """
    p = probs.float()
    n = p.shape[1]
    maps = {"E": (p * torch.log(p + EPSILON)).sum(1) / math.log(1 / n)}
    top = p.topk(2, dim=1).values
    maps["D"] = 1 - top[:, 0] + top[:, 1]
    if rule is not None:
        maps["R"] = cost_margin(p, rule, priors, roi)
    if expected_entropy is not None:
        maps["MI"] = (entropy(p) - expected_entropy.float()).clamp_min(0)
    return maps


def cost_margin(
    probs: Tensor, rule: Rule, priors: Tensor | None = None, roi: Tensor | None = None
) -> Tensor:
    """(B, H, W) (second-lowest − lowest expected cost) / largest off-diagonal cost of ``rule``.

    Expected costs are ``Σ_k C[k', k] q_k`` for each decision k' (rows of C: the predicted class,
    a defer row last), with ``q = p / π_α`` for a rule with priors, else ``q = p``; a regional
    rule: with the matrix of the pixel's RoI in ``roi``, and its largest off-diagonal cost.
    """
    pi = None
    if rule.priors_alpha:
        pi = given_priors(priors, f"the rule {rule.name}")
        pi = adapted_priors(pi.double(), rule.priors_alpha)
    low = expected_costs(probs, rule.cost, pi, roi).topk(2, dim=1, largest=False).values
    largest = off_diagonal(cost_or_symmetric(rule.cost, probs.shape[1])).amax(-1)
    if rule.regional:  # each pixel's own matrix's
        largest = largest.to(low.device)[torch.as_tensor(roi, device=low.device).long()]
    return ((low[:, 1] - low[:, 0]) / largest.to(low)).float()
