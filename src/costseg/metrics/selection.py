"""Choosing among evaluated rules: targets such as ``person:roi1:recall>=0.99`` and best points.

Pure functions on results; nothing here runs a network.

>>> parse_target("person:roi1:recall>=0.99")
Target(cls=11, roi=1, metric='recall', op='>=', value=0.99)
>>> parse_target("person:roi1:handled_recall>=0.999").metric
'handled_recall'
>>> parse_metric("all:roi1:coverage")         # the RoI's coverage over all classes
Metric(cls=None, roi=1, metric='coverage')
"""

from __future__ import annotations

import math
import re
from collections.abc import Sequence
from dataclasses import dataclass
from typing import NamedTuple

import torch

from costseg.classes import CLASS_NAMES, ROI_IDS, class_index
from costseg.metrics.names import (
    DEFER_RATES,
    HIGHER_IS_BETTER,
    INSTANCE_RATES,
    PIXEL_RATES,
    TARGET_METRICS,
)

_OPS = {">=": float.__ge__, "<=": float.__le__, ">": float.__gt__, "<": float.__lt__}


ALL_CLASSES = "all"
"""The class of ``all:roi:coverage``: every class of the RoI together (cls None)."""

ALL_CLASS_METRICS = ("coverage",)
"""The metrics named over all classes: coverage = 1 − the RoI's deferred rate
(docs/definitions.md §14)."""


class Metric(NamedTuple):
    cls: int | None
    roi: int
    metric: str


class Target(NamedTuple):
    cls: int | None
    roi: int
    metric: str
    op: str
    value: float


def parse_metric(text: str, class_names: Sequence[str] = CLASS_NAMES) -> Metric:
    """``class:roi:metric`` (e.g. ``person:roi1:precision``, or ``all:roi1:coverage`` over all
    classes: cls None) → Metric; ValueError if malformed."""
    parts = text.split(":")
    if len(parts) != 3:
        raise ValueError(
            f"cannot parse {text!r}: expected class:roi:metric, e.g. person:roi1:recall"
        )
    name, roi, metric = (p.strip() for p in parts)
    if roi not in ROI_IDS:
        raise ValueError(f"unknown RoI {roi!r} in {text!r}: expected one of {', '.join(ROI_IDS)}")
    if metric not in TARGET_METRICS:
        raise ValueError(
            f"unknown metric {metric!r} in {text!r}: expected one of {', '.join(TARGET_METRICS)}"
        )
    if name == ALL_CLASSES:
        if metric not in ALL_CLASS_METRICS:
            raise ValueError(
                f"{text!r}: over all classes only {', '.join(ALL_CLASS_METRICS)} is measured, "
                "e.g. all:roi1:coverage"
            )
        return Metric(None, ROI_IDS[roi], metric)
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
    metric = parse_metric(match.group(1), class_names)
    if not 0 <= value <= 1:  # every target metric is a rate
        raise ValueError(f"{metric.metric} is a rate in [0, 1]: the target {text!r} is outside")
    return Target(*metric, match.group(2), value)


def metric_values(
    pixels: dict[str, torch.Tensor],
    segments: dict[str, torch.Tensor],
    metric: Metric | Target,
    class_ids: Sequence[int],
    instances: dict[str, torch.Tensor] | None = None,
) -> torch.Tensor:
    """(K,) values of ``metric`` for every rule of a group (NaN where undefined)."""
    if metric.cls is None:  # all:roi:coverage
        return pixels["coverage_all_classes"][:, metric.roi]
    if metric.metric in (*PIXEL_RATES, *DEFER_RATES):
        return pixels[metric.metric][:, metric.roi, metric.cls]
    if metric.metric in INSTANCE_RATES:
        measured = [] if not instances else instances["classes"].tolist()
        if metric.cls not in measured:
            name = CLASS_NAMES[metric.cls]
            raise ValueError(
                f"instance_recall of {name!r} was not measured: it needs instance ids and "
                f"{name!r} in --classes (an instance class)"
            )
        return instances["instance_recall"][:, measured.index(metric.cls), metric.roi]
    if metric.cls not in class_ids:
        name = CLASS_NAMES[metric.cls]
        raise ValueError(f"{metric.metric} needs {name!r} in --classes (a segment metric)")
    return segments[metric.metric][:, list(class_ids).index(metric.cls), metric.roi]


def meets(values: torch.Tensor, target: Target) -> torch.Tensor:
    """(K,) bool: which values meet ``target`` (NaN never does).

    >>> meets(torch.tensor([0.5, float("nan"), 0.99]), parse_target("person:roi1:recall>=0.9"))
    tensor([False, False,  True])
    """
    op = _OPS[target.op]
    return torch.tensor([not math.isnan(v) and op(v, target.value) for v in values.tolist()])


def best_points(
    values: torch.Tensor, allowed: torch.Tensor, prefer: Sequence[float] | None = None
) -> list[int]:
    """Indices of the allowed points with the largest value (NaN values never qualify), in
    index order, or by descending ``prefer`` (e.g. the defer cost: ties to the larger).

    >>> ok = torch.tensor([True, True, True, False])
    >>> best_points(torch.tensor([0.3, 0.9, 0.9, 1.0]), ok)
    [1, 2]
    >>> best_points(torch.tensor([0.3, 0.9, 0.9, 1.0]), ok, prefer=[0.0, 0.1, 0.2, 0.3])
    [2, 1]
    """
    ok = allowed & ~values.isnan()
    if not ok.any():
        return []
    best = values[ok].max()
    points = [int(i) for i in (ok & (values == best)).nonzero().squeeze(1)]
    return points if prefer is None else sorted(points, key=lambda i: -prefer[i])


@dataclass
class Choice:
    """The answer to ``--target T --maximize M`` over a group of rules.

    Attributes:
        target, maximize: the texts asked.
        points: indices of the rules that meet the target with the best value (may be empty),
            the preferred first (:func:`best_points`).
        value: the best value of ``maximize`` among them (NaN if none).
        best_reached: the best value of the target's metric on any rule (to say how close).
    """

    target: str
    maximize: str
    points: list[int]
    value: float
    best_reached: float


def choose(
    pixels: dict[str, torch.Tensor],
    segments: dict[str, torch.Tensor],
    target: str,
    maximize: str,
    class_ids: Sequence[int],
    instances: dict[str, torch.Tensor] | None = None,
    prefer: Sequence[float] | None = None,
) -> Choice:
    """The rules meeting ``target`` with the largest ``maximize`` (measured on these images);
    ties ordered by descending ``prefer`` (``RuleGroup.prefer``), else by index."""
    t, goal = parse_target(target), parse_metric(maximize)
    target_values = metric_values(pixels, segments, t, class_ids, instances)
    values = metric_values(pixels, segments, goal, class_ids, instances)
    points = best_points(values, meets(target_values, t), prefer)
    reached = target_values[~target_values.isnan()]
    best = math.nan
    if len(reached):
        best = (reached.max() if t.op in (">=", ">") else reached.min()).item()
    value = values[points[0]].item() if points else math.nan
    return Choice(target, maximize, points, value, best)


def risk_level(target: Target) -> float:
    """α of a guarantee: ``recall >= v`` bounds the loss 1 − recall by 1 − v (same for
    precision, instance recall and the rates of deferral); ``fp_rate <= v`` bounds the rate
    itself by v.

    >>> round(risk_level(parse_target("person:roi1:recall>=0.95")), 6)
    0.05
    """
    if target.metric in HIGHER_IS_BETTER:
        if target.op not in (">=", ">"):
            raise ValueError(f"a certificate bounds {', '.join(HIGHER_IS_BETTER)} >= a value")
        return 1 - target.value
    if target.op not in ("<=", "<"):
        raise ValueError("a certificate bounds fp_rate or fn_rate <= a value")
    return target.value


def certifiable_level(text: str, flag: str) -> float:
    """α of the target ``text`` given to ``flag`` (``--target``, ``--require``); ValueError
    naming both unless α lies in (0, 1), a level a certificate can reach.

    >>> certifiable_level("person:roi1:recall>=1", "--require")
    Traceback (most recent call last):
    ValueError: --require person:roi1:recall>=1 leaves no risk level α in (0, 1)
    """
    try:
        alpha = risk_level(parse_target(text))
    except ValueError as err:
        raise ValueError(f"{flag} {text}: {err}") from None
    if not 0 < alpha < 1:
        raise ValueError(f"{flag} {text} leaves no risk level α in (0, 1)")
    return alpha
