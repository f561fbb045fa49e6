"""The named rules of ``--cost``: the presets, ``ml`` and YAML cost files (docs/definitions.md §1,
§2; a regional file, §21), decided together as one group.

A :class:`~costseg.rules.base.Rule` is a cost matrix (``None`` = the symmetric one; a regional
value system's stack, decided with the RoI map) and whether it acts on ``p / π`` with the
pixel-wise priors π (``ml`` is the symmetric matrix on ``p / π``).

>>> [r.name for r in parse_rules(["robotistic", "ml"])]
['robotistic', 'ml']
>>> rules_group(parse_rules(["egoistic"])).columns
[{'matrix': 'egoistic'}]
>>> rules_group(parse_rules(["egoistic"], defer=0.5)).columns
[{'matrix': 'egoistic', 'defer': 0.5}]
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import torch

from costseg.classes import CLASS_NAMES
from costseg.costs import (
    PRESETS,
    cost_name,
    cost_or_symmetric,
    has_defer_row,
    load_cost,
    with_defer,
)
from costseg.decision import decide
from costseg.decision.label_maps import empty_labels
from costseg.rules.base import (
    DEFER_COLUMN,
    Rule,
    RuleGroup,
    adapted_priors,
    given_priors,
    needs_priors,
    needs_roi,
)

RULE_NAMES = (*PRESETS, "ml")


def parse_rules(
    names: Sequence[str], class_names: Sequence[str] = CLASS_NAMES, defer: float | None = None
) -> list[Rule]:
    """Rules from names: the presets, ``ml``, or paths to YAML cost files (a file with
    ``regions:``: a regional rule, docs/definitions.md §21), each named by its file's ``name:``
    (else, or where two files share it, by its file name).

    Args:
        names: the rules of ``--cost``.
        class_names: the network's classes.
        defer: ``--defer``: every rule gains a defer row of this cost (docs/definitions.md §14;
            a regional rule: every matrix of it); a cost file may instead hold its own
            ``defer:`` section.

    Raises:
        ValueError: an unknown name (listing the valid ones), an invalid cost file, or ``defer``
            given for a cost file that has a defer row of its own.

    >>> parse_rules(["ml"], ["a", "b"], defer=0.25)[0].cost.tolist()
    [[0.0, 1.0], [1.0, 0.0], [0.25, 0.25]]
    """
    rules = []
    for name in names:
        if name == "ml":
            rule = Rule("ml", None, 1.0)
        elif name in PRESETS or Path(name).suffix in (".yaml", ".yml"):
            rule = Rule(cost_name(name), load_cost(name, class_names))
        else:
            raise ValueError(
                f"unknown cost {name!r}: expected one of {', '.join(RULE_NAMES)} "
                "or a path to a .yaml cost file"
            )
        if defer is not None:
            if rule.cost is not None and has_defer_row(rule.cost):
                raise ValueError(
                    f"--defer with {name}, which has a defer row of its own: leave it out"
                )
            cost = cost_or_symmetric(rule.cost, len(class_names))
            rule = Rule(rule.name, with_defer(cost, defer), rule.priors_alpha)
        rules.append(rule)
    rules = _distinct_names(rules, names)
    if len({r.name for r in rules}) != len(rules):
        raise ValueError(f"cost rules must have distinct names, got {[r.name for r in rules]}")
    return rules


def _distinct_names(rules: list[Rule], names: Sequence[str]) -> list[Rule]:
    """``rules``, those of files whose ``name:`` another rule shares named by their file name
    instead (two designed files, both ``name: designed``)."""
    taken = [r.name for r in rules]
    return [
        Rule(Path(given).stem, r.cost, r.priors_alpha)
        if taken.count(r.name) > 1 and Path(given).suffix in (".yaml", ".yml")
        else r
        for r, given in zip(rules, names, strict=True)
    ]


def apply_rules(
    probs: torch.Tensor,
    rules: Sequence[Rule],
    priors: torch.Tensor | None = None,
    roi: torch.Tensor | None = None,
) -> torch.Tensor:
    """Decisions of every rule: probs (B, N, H, W) → (B, K, H, W) int64.

    Each rule is one :func:`decide` call (for a few named rules faster than one
    :func:`decide_mixtures` pass with identity weights: scripts/bench_predict.py); a rule with
    priors needs ``priors`` ((N,) or (N, H, W)), a regional rule ``roi`` ((H, W) RoI ids).
    """
    shape = probs.shape[0], len(rules), *probs.shape[2:]
    out = empty_labels(*shape, dtype=torch.long, device=probs.device)
    for k, rule in enumerate(rules):
        if rule.regional:
            out[:, k] = decide(probs, rule.cost, roi=_given_roi(roi, rule))
        elif not rule.priors_alpha:
            out[:, k] = decide(probs, rule.cost)
        else:
            pi = given_priors(priors, f"the rule {rule.name}")
            out[:, k] = decide(probs, rule.cost, adapted_priors(pi, rule.priors_alpha))
    return out


def _given_roi(roi: torch.Tensor | None, rule: Rule) -> torch.Tensor:
    if roi is None:
        raise ValueError(f"the rule {rule.name} decides each RoI with its own matrix: a RoI map")
    return roi


def rule_columns(rule: Rule, defer: bool) -> dict[str, object]:
    """The columns that identify a named rule in result rows: its name and, with ``defer``
    (some rule of its group defers), its defer cost."""
    return {"matrix": rule.name} | ({DEFER_COLUMN: rule.defer_cost} if defer else {})


@dataclass(frozen=True)
class NamedRules:
    """``probs, priors, roi → (B, K, H, W)`` for named rules (a class, not a closure: groups
    travel to DDP worker processes with the LightningModule, so they must pickle)."""

    rules: tuple[Rule, ...]

    def __call__(self, probs: torch.Tensor, priors: torch.Tensor | None, roi=None) -> torch.Tensor:
        return apply_rules(probs, self.rules, priors, roi)


def rules_group(rules: Sequence[Rule]) -> RuleGroup:
    """The named rules of ``--cost`` as one group (with FP/FN location maps); where one of them
    defers, each rule's defer cost is a column (:attr:`Rule.defer_cost`)."""
    rules = list(rules)
    defer = any(r.defers for r in rules)
    return RuleGroup(
        "rules",
        [r.name for r in rules],
        NamedRules(tuple(rules)),
        [rule_columns(r, defer) for r in rules],
        is_named=True,
        heatmaps=True,
        needs_priors=needs_priors(rules),
        needs_roi=needs_roi(rules),
        rules=rules,
    )
