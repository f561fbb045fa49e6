"""Decision rules and rule groups: what ``--cost``, ``--sweep`` and ``--alpha_sweep`` decide.

A :class:`Rule` is a cost matrix (``None`` = the symmetric one) and whether it acts on ``p / π``
with the pixel-wise priors π (``ml`` is the symmetric matrix on ``p / π``). A
:class:`RuleGroup` is K rules decided together from one softmax: ``probs → (B, K, H, W)``. The
named rules, the value-space triangle and the prior-adapted α path are each one group; the
evaluation loop and validation feed every group's label maps to the metrics.

>>> [r.name for r in parse_rules(["robotistic", "ml"])]
['robotistic', 'ml']
>>> grid_group(["robotistic", "altruistic", "egoistic"], 0.5).names[:2]
['w=1.00/0.00/0.00', 'w=0.50/0.50/0.00']
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import torch

from costseg.classes import CLASS_NAMES
from costseg.costs import PRESETS, barycentric_grid, load_cost, rescale, symmetric_cost
from costseg.decision import decide, decide_mixtures
from costseg.decision.label_maps import empty_labels

RULE_NAMES = (*PRESETS, "ml")
Decider = Callable[[torch.Tensor, torch.Tensor | None], torch.Tensor]


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


@dataclass
class RuleGroup:
    """K rules decided together: ``decide(probs (B,N,H,W), priors) → (B, K, H, W)``.

    Attributes:
        kind: ``"rules"`` (named rules), ``"grid"`` (value-space triangle) or ``"alpha"``.
        names: the K rule names.
        decide: the decision function.
        columns: per rule, the columns that identify it in result rows.
        heatmaps: whether FP/FN location maps are kept (off for sweeps of many rules).
        rules: the named rules (kind "rules").
        vertices: (3, N, N) vertex matrices and ``weights`` (K, 3) (kind "grid").
        note: how the group was built, for every output that shows it.
        temperature: decide on ``softmax(z / T)`` of the raw logits instead of the
            probabilities every other group sees (the temperature sweep of SPEC §6).
    """

    kind: str
    names: list[str]
    decide: Decider
    columns: list[dict[str, object]]
    heatmaps: bool = False
    rules: list[Rule] = field(default_factory=list)
    vertices: torch.Tensor | None = None
    weights: torch.Tensor | None = None
    note: str = ""
    temperature: float | None = None


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
    n = probs.shape[1]
    shape = probs.shape[0], len(rules), *probs.shape[2:]
    out = empty_labels(*shape, dtype=torch.long, device=probs.device)
    plain = [k for k, r in enumerate(rules) if not r.priors_alpha]
    if plain:
        vertices = torch.stack([_matrix(rules[k].cost, n) for k in plain])
        weights = torch.eye(len(plain), dtype=torch.float64)
        out[:, plain] = decide_mixtures(probs, vertices, weights).long()
    for k, rule in enumerate(rules):
        if rule.priors_alpha:
            if priors is None:
                raise ValueError(f"rule {rule.name!r} needs pixel-wise priors")
            out[:, k] = decide(probs, rule.cost, adapted_priors(priors, rule.priors_alpha))
    return out


def _matrix(cost: torch.Tensor | None, n: int) -> torch.Tensor:
    return symmetric_cost(n) if cost is None else cost


@dataclass(frozen=True)
class _NamedRules:
    """``probs, priors → (B, K, H, W)`` for named rules (a class, not a closure: groups travel
    to DDP worker processes with the LightningModule, so they must pickle)."""

    rules: tuple[Rule, ...]

    def __call__(self, probs: torch.Tensor, priors: torch.Tensor | None) -> torch.Tensor:
        return apply_rules(probs, self.rules, priors)


@dataclass(frozen=True)
class _Mixtures:
    vertices: torch.Tensor
    weights: torch.Tensor

    def __call__(self, probs: torch.Tensor, priors: torch.Tensor | None) -> torch.Tensor:
        return decide_mixtures(probs, self.vertices, self.weights)


@dataclass(frozen=True)
class _PriorAdapted:
    cost: torch.Tensor | None
    alphas: tuple[float, ...]

    def __call__(self, probs: torch.Tensor, priors: torch.Tensor | None) -> torch.Tensor:
        if priors is None:
            raise ValueError("the α sweep needs pixel-wise priors")
        return torch.stack(
            [decide(probs, self.cost, adapted_priors(priors, a)) for a in self.alphas], 1
        )


def rules_group(rules: Sequence[Rule]) -> RuleGroup:
    """The named rules of ``--cost`` as one group (with FP/FN location maps)."""
    rules = list(rules)
    return RuleGroup(
        "rules",
        [r.name for r in rules],
        _NamedRules(tuple(rules)),
        [{"matrix": r.name} for r in rules],
        heatmaps=True,
        rules=rules,
    )


def vertex_matrices(
    names: Sequence[str], scaling: str = "none", class_names: Sequence[str] = CLASS_NAMES
) -> torch.Tensor:
    """The three vertex cost matrices (3, N, N), optionally rescaled to unit mean cost."""
    if len(names) != 3:
        raise ValueError(f"a sweep needs exactly 3 vertex costs, got {len(names)}: {list(names)}")
    if scaling not in ("none", "mean"):
        raise ValueError(f"vertex scaling must be 'none' or 'mean', got {scaling!r}")
    rules = parse_rules(names, class_names)
    if any(r.priors_alpha for r in rules):
        raise ValueError("'ml' uses pixel-wise priors and is no matrix: it cannot be a vertex")
    vertices = torch.stack([_matrix(r.cost, len(class_names)) for r in rules])
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
        _Mixtures(vertices, weights),
        [dict(zip(("alpha", "beta", "gamma"), w, strict=True)) for w in weights.tolist()],
        vertices=vertices,
        weights=weights,
        note=f"vertices: {', '.join(vertex_names)}; vertex scaling: {scaling}",
    )


def alpha_grid(step: float) -> list[float]:
    """α = 0, step, …, 1.

    >>> alpha_grid(0.25)
    [0.0, 0.25, 0.5, 0.75, 1.0]
    """
    n = round(1 / step) if step > 0 else 0
    if n < 1 or not math.isclose(n * step, 1.0, rel_tol=1e-9):
        raise ValueError(f"alpha step must be 1/n for a whole number n >= 1, got {step}")
    return [i / n for i in range(n + 1)]


def alpha_group(
    step: float, cost_name: str | None = None, class_names: Sequence[str] = CLASS_NAMES
) -> RuleGroup:
    """The prior-adapted rule on ``p / π_α`` for α = 0, step, …, 1 (0 = Bayes, 1 = ML)."""
    base = parse_rules([cost_name], class_names)[0] if cost_name else None
    if base is not None and base.priors_alpha:
        raise ValueError("--alpha_cost must be a cost matrix, not 'ml'")
    cost, label = (base.cost, base.name) if base else (None, "robotistic")
    alphas = alpha_grid(step)
    return RuleGroup(
        "alpha",
        [f"{label}@alpha={a:.2f}" for a in alphas],
        _PriorAdapted(cost, tuple(alphas)),
        [{"prior_alpha": a} for a in alphas],
        note=f"{label} on p/π_α, π_α = (1-α) + απ",
    )


TEMPERATURES = (0.5, 0.75, 1.0, 1.25, 1.5, 1.75, 2.0)


def temperature_group(rules: Sequence[Rule], temperature: float) -> RuleGroup:
    """The named rules on ``softmax(z / T)`` (SPEC §6: cost rules move with T, argmax does not).

    >>> temperature_group(parse_rules(["egoistic"]), 0.5).names
    ['egoistic@T=0.50']
    """
    group = rules_group(rules)
    group.kind, group.heatmaps, group.temperature = "temperature", False, temperature
    group.names = [f"{r.name}@T={temperature:.2f}" for r in rules]
    group.columns = [{"matrix": r.name, "temperature": temperature} for r in rules]
    return group
