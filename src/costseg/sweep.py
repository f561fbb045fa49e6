"""The value-space triangle (SPEC §2) and the prior-adapted α sweep (SPEC §1).

Every grid point ``αC_R + βC_A + γC_E`` is decided by mixing the three vertex cost maps, so a
sweep costs one network pass and three cost maps per image. Constraints such as
``person:roi1:recall>=0.99`` pick the grid points a user can live with.

>>> parse_target("person:roi1:recall>=0.99")
Target(cls=11, roi=1, metric='recall', op='>=', value=0.99)
"""

from __future__ import annotations

import math
import re
from collections.abc import Sequence
from typing import NamedTuple

import torch

from costseg.classes import CLASS_NAMES, class_index
from costseg.costs import rescale
from costseg.decision import decide, decide_mixtures
from costseg.evaluation import RuleGroup
from costseg.rules import adapted_priors, parse_rules

METRICS = ("precision", "recall", "fp_rate", "fn_rate")
ROI_IDS = {"roi0": 0, "image": 0, "roi1": 1, "street": 1, "roi2": 2, "sidewalk": 2}
ROI_IDS |= {"roi3": 3, "building": 3, "roi4": 4, "sky": 4}
_OPS = {">=": float.__ge__, "<=": float.__le__, ">": float.__gt__, "<": float.__lt__}


class Metric(NamedTuple):
    cls: int
    roi: int
    metric: str


class Target(NamedTuple):
    cls: int
    roi: int
    metric: str
    op: str
    value: float


def vertex_matrices(
    names: Sequence[str], scaling: str = "none", class_names: Sequence[str] = CLASS_NAMES
) -> torch.Tensor:
    """The three vertex cost matrices (3, N, N), optionally rescaled to unit mean cost."""
    if len(names) != 3:
        raise ValueError(f"a sweep needs exactly 3 vertex costs, got {len(names)}: {list(names)}")
    rules = parse_rules(names, class_names)
    if any(r.priors_alpha for r in rules):
        raise ValueError("'ml' uses pixel-wise priors and is no matrix: it cannot be a vertex")
    n = len(class_names)
    vertices = torch.stack(
        [r.cost if r.cost is not None else 1 - torch.eye(n, dtype=torch.float64) for r in rules]
    )
    if scaling not in ("none", "mean"):
        raise ValueError(f"vertex scaling must be 'none' or 'mean', got {scaling!r}")
    return rescale(vertices) if scaling == "mean" else vertices


def point_name(weights: Sequence[float]) -> str:
    """``w=0.70/0.20/0.10`` for the grid point (α, β, γ)."""
    return "w=" + "/".join(f"{w:.2f}" for w in weights)


def sweep_group(vertices: torch.Tensor, weights: torch.Tensor) -> RuleGroup:
    """All grid points as one rule group, decided by mixing vertex cost maps."""
    return RuleGroup(
        [point_name(w) for w in weights.tolist()],
        lambda probs, priors: decide_mixtures(probs, vertices, weights),
        heatmaps=False,
    )


def alpha_group(cost: torch.Tensor | None, alphas: Sequence[float], label: str) -> RuleGroup:
    """The prior-adapted rule on ``p / π_α`` for each α (0 = Bayes, 1 = ML), one cost matrix."""

    def decide_all(probs: torch.Tensor, priors: torch.Tensor | None) -> torch.Tensor:
        if priors is None:
            raise ValueError("the α sweep needs pixel-wise priors in the checkpoint")
        return torch.stack([decide(probs, cost, adapted_priors(priors, a)) for a in alphas], 1)

    return RuleGroup([f"{label}@alpha={a:.2f}" for a in alphas], decide_all, heatmaps=False)


def alpha_grid(step: float) -> list[float]:
    """α = 0, step, …, 1."""
    n = round(1 / step) if step > 0 else 0
    if n < 1 or not math.isclose(n * step, 1.0, rel_tol=1e-9):
        raise ValueError(f"alpha step must be 1/n for a whole number n >= 1, got {step}")
    return [i / n for i in range(n + 1)]


def parse_metric(text: str, class_names: Sequence[str] = CLASS_NAMES) -> Metric:
    """``class:roi:metric`` (e.g. ``person:roi1:precision``) → Metric; ValueError if malformed."""
    parts = text.split(":")
    if len(parts) != 3:
        raise ValueError(
            f"cannot parse {text!r}: expected class:roi:metric, e.g. person:roi1:recall"
        )
    name, roi, metric = (p.strip() for p in parts)
    if roi not in ROI_IDS:
        raise ValueError(f"unknown RoI {roi!r} in {text!r}: expected one of {', '.join(ROI_IDS)}")
    if metric not in METRICS:
        raise ValueError(
            f"unknown metric {metric!r} in {text!r}: expected one of {', '.join(METRICS)}"
        )
    return Metric(class_index(name, class_names), ROI_IDS[roi], metric)


def parse_target(text: str, class_names: Sequence[str] = CLASS_NAMES) -> Target:
    """``class:roi:metric OP value`` with OP in >=, <=, >, < → Target; ValueError if malformed."""
    match = re.fullmatch(r"\s*(.+?)\s*(>=|<=|>|<)\s*([-+0-9.eE]+)\s*", text)
    if match is None:
        raise ValueError(
            f"cannot parse target {text!r}: expected class:roi:metric>=value, "
            "e.g. person:roi1:recall>=0.99"
        )
    try:
        value = float(match.group(3))
    except ValueError:
        raise ValueError(f"cannot parse the number in target {text!r}") from None
    return Target(*parse_metric(match.group(1), class_names), match.group(2), value)


def metric_values(result: dict, metric: Metric, class_pos: int | None) -> torch.Tensor:
    """(K,) values of ``metric`` for every rule of a group result (NaN where undefined)."""
    if metric.metric in ("precision", "recall"):
        return result["pixels"][metric.metric][:, metric.roi, metric.cls]
    if class_pos is None:
        raise ValueError(f"{metric.metric} needs the class in --classes (segment metrics)")
    return result["segments"][metric.metric][:, class_pos, metric.roi]


def best_points(values: torch.Tensor, target_values: torch.Tensor, target: Target) -> list[int]:
    """Indices of the points meeting ``target`` with the largest value (NaN never qualifies)."""
    ok = torch.tensor(
        [
            not math.isnan(t) and not math.isnan(v) and _OPS[target.op](float(t), target.value)
            for t, v in zip(target_values.tolist(), values.tolist(), strict=True)
        ]
    )
    if not ok.any():
        return []
    best = values[ok].max()
    return [int(i) for i in (ok & (values == best)).nonzero().squeeze(1)]
