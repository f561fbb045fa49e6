"""Named decision rules: what ``--cost robotistic altruistic ml my.yaml`` means.

A rule is a cost matrix (``None`` = the symmetric one) and whether it acts on ``p / π`` with the
pixel-wise priors π (``ml`` is the symmetric matrix on ``p / π``). :func:`apply_rules` evaluates
all rules of a batch in one pass over the probabilities where it can.

>>> [r.name for r in parse_rules(["robotistic", "ml"])]
['robotistic', 'ml']
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import torch

from costseg.classes import CLASS_NAMES
from costseg.costs import PRESETS, load_cost
from costseg.decision import decide, decide_mixtures

RULE_NAMES = (*PRESETS, "ml")


@dataclass(frozen=True)
class Rule:
    """One decision rule.

    Attributes:
        name: shown in tables, files and TensorBoard tags.
        cost: (N, N) float64 matrix; ``None`` = the symmetric matrix.
        priors_alpha: 0 = no priors; α in (0, 1] = the rule on ``p / π_α`` with
            ``π_α = (1 - α) + α π`` (1 = maximum likelihood when ``cost`` is None).
    """

    name: str
    cost: torch.Tensor | None
    priors_alpha: float = 0.0


def parse_rules(names: Sequence[str], class_names: Sequence[str] = CLASS_NAMES) -> list[Rule]:
    """Rules from names: the presets, ``ml``, or paths to YAML cost files.

    Raises:
        ValueError: an unknown name (listing the valid ones) or an invalid cost file.
    """
    rules = []
    for name in names:
        if name == "ml":
            rules.append(Rule("ml", None, 1.0))
        elif name in PRESETS or Path(name).suffix in (".yaml", ".yml"):
            rules.append(Rule(Path(name).stem, load_cost(name, class_names)))
        else:
            raise ValueError(
                f"unknown cost {name!r}: expected one of {', '.join(RULE_NAMES)} "
                "or a path to a .yaml cost file"
            )
    if len({r.name for r in rules}) != len(rules):
        raise ValueError(f"cost rules must have distinct names, got {[r.name for r in rules]}")
    return rules


def adapted_priors(priors: torch.Tensor, alpha: float) -> torch.Tensor:
    """Bayes ↔ ML interpolation of SPEC §1: ``π_α = (1 - α)·1 + α·π``.

    >>> adapted_priors(torch.tensor([0.2, 0.8], dtype=torch.float64), 0.5).tolist()
    [0.6, 0.9]
    """
    return (1 - alpha) + alpha * priors


def apply_rules(
    probs: torch.Tensor, rules: Sequence[Rule], priors: torch.Tensor | None = None
) -> torch.Tensor:
    """Decisions of every rule: probs (B, N, H, W) → (B, K, H, W) int64.

    Rules without priors share one pass (:func:`decide_mixtures` with identity weights); each
    rule with priors needs ``priors`` ((N,) or (N, H, W)) and one pass of its own.
    """
    out = torch.empty(
        probs.shape[0], len(rules), *probs.shape[2:], dtype=torch.long, device=probs.device
    )
    plain = [k for k, r in enumerate(rules) if not r.priors_alpha]
    if plain:
        vertices = torch.stack([_matrix(rules[k], probs.shape[1]) for k in plain])
        weights = torch.eye(len(plain), dtype=torch.float64)
        out[:, plain] = decide_mixtures(probs, vertices, weights).long()
    for k, rule in enumerate(rules):
        if rule.priors_alpha:
            if priors is None:
                raise ValueError(f"rule {rule.name!r} needs pixel-wise priors")
            out[:, k] = decide(probs, rule.cost, adapted_priors(priors, rule.priors_alpha))
    return out


def _matrix(rule: Rule, num_classes: int) -> torch.Tensor:
    if rule.cost is None:
        return 1 - torch.eye(num_classes, dtype=torch.float64)
    return rule.cost
