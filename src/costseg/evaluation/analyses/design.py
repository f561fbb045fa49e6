"""``--design SPACE``: a cost matrix designed from several requirements and certified by Pareto
Testing on the held-out images (docs/definitions.md §20).

The held-out images split in two: the first half (D1) is searched (every candidate of the space
scored by one fused decide-and-count pass, on a seeded share of each image's pixels), the second
(D2) tests the D1 Pareto front in order on every pixel. The certified matrix best by the objective
on all held-out images, and the best certified point of the triangle beside it, join the rule
groups, so the reported images measure them with every usual row.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
import torch

from costseg.calibration.design_search import search
from costseg.calibration.guarantee import defined_risks
from costseg.calibration.pareto_testing import choose, pareto_testing
from costseg.classes import CLASS_NAMES
from costseg.costs import cost_or_symmetric
from costseg.decision import count_decisions, decide, prepare_counts, subsample
from costseg.evaluation.analyses import Analysis, Context, Provided, Seen
from costseg.evaluation.settings import DesignSettings
from costseg.metrics.requirements import Requirements
from costseg.report.design import DESIGNED_FAMILY, DesignOutcome, SearchOutcome
from costseg.rules import Rule, RuleGroup, parse_rules, vertex_matrices
from costseg.rules.design_spaces import (
    AggregateSpace,
    LagrangianSpace,
    TriangleSpace,
    aggregate_template,
    lagrangian_directions,
)
from costseg.rules.named import NamedRules, rule_columns

Space = TriangleSpace | LagrangianSpace | AggregateSpace


class Design(Analysis):
    settings: DesignSettings

    def fit(self) -> Provided:
        self.outcome = design(self.context, self.settings)
        group = designed_group(self.outcome)
        return Provided(groups=() if group is None else (group,))

    def result(self) -> DesignOutcome:
        return self.outcome


def design(context: Context, settings: DesignSettings) -> DesignOutcome:
    """Search every space of :func:`spaces` on D1, certify each one's Pareto front on D2."""
    req = Requirements.parse(settings.requirements, settings.maximize, settings.minimize)
    delta, seed = settings.delta, settings.seed
    n = len(context.held_out)
    n1 = n // 2
    share = 1.0 if req.label_maps else settings.pixels
    found = SearchImages.of(context, n1, share, req, seed)
    searched = []  # (candidates, their (n1, L, K) per-image losses on D1)
    for space in spaces(settings, req):
        losses: list[np.ndarray] = []
        candidates = search(
            space, found.scorer(req, losses.append), req.alphas, settings.budget, seed,
            req.maximize,
        )  # fmt: skip
        searched.append((candidates, np.stack(losses, 1)))
    fronts = [_front(losses, c.objective, req, delta) for c, losses in searched]
    tested = _test_fronts(
        context, n1, req, [(c, f) for (c, _), f in zip(searched, fronts, strict=True)]
    )
    outcomes = []
    for i, ((candidates, losses_d1), (losses_d2, objective_all)) in enumerate(
        zip(searched, tested, strict=True)
    ):
        result = pareto_testing(
            losses_d1, losses_d2, req.alphas, delta, candidates.objective, req.maximize
        )
        chosen = choose(result, objective_all, req.maximize)
        outcomes.append(SearchOutcome(candidates, result, chosen, objective_all, designed=i == 0))
    return DesignOutcome(req, delta, n1, n - n1, share, seed, outcomes)


def spaces(settings: DesignSettings, req: Requirements) -> list[Space]:
    """The space of ``--design`` and, when it is another, the triangle (the comparison)."""
    defer = settings.defer
    grids = max(1, len(defer))
    budget = settings.budget // grids
    n = max(1, int((math.sqrt(8 * budget + 1) - 3) / 2))  # (n + 1)(n + 2) / 2 <= budget
    corners = vertex_matrices(list(settings.vertices), settings.vertex_scaling)
    triangle = TriangleSpace(corners, 1 / n, defer)
    if settings.space == "triangle":
        return [triangle]
    if settings.space == "lagrangian":
        base = parse_rules([settings.base or "robotistic"])[0]
        pairs = [(t.cls, t.metric) for t in req.constraints]
        size = max(2, int(budget ** (1 / len(pairs)) + 1e-9))
        base_cost = cost_or_symmetric(base.cost, len(CLASS_NAMES))
        own = LagrangianSpace(base_cost, lagrangian_directions(pairs, len(CLASS_NAMES)), size,
                              defer_costs=defer)  # fmt: skip
    else:
        box = (min(defer), max(defer)) if defer else None
        own = AggregateSpace(aggregate_template(settings.base or "altruistic"), defer_box=box)
    return [own, triangle]


def d1_images(first: int, size: int, n1: int) -> int:
    """How many images of a batch of ``size`` held-out images, the first at position ``first``,
    belong to D1 (the first ``n1`` held-out images); the rest belong to D2.

    >>> d1_images(0, 4, 6), d1_images(4, 4, 6), d1_images(8, 4, 6)
    (4, 2, 0)
    """
    return max(0, min(size, n1 - first))


def pixel_seeds(seed: int, first: int, count: int) -> list[int]:
    """The seeds of the search's pixel draws of ``count`` images, the first at position
    ``first`` among the held-out images: one per image, so any batch size draws the same."""
    return list(range(seed + first, seed + first + count))


class Pooled:
    """One matrix's decision counts pooled over images: the (N, N) confusion and the pixels
    decided as argmax, from which the objective is computed (:meth:`Requirements.value`)."""

    def __init__(self) -> None:
        self.confusion, self.agree = 0, 0

    def add(self, counts) -> None:
        """Add a batch's counts (:func:`costseg.decision.count_decisions`)."""
        self.confusion = self.confusion + counts.confusion.sum(0)
        self.agree = self.agree + counts.agree.sum()

    def value(self, req: Requirements) -> float:
        return req.value(self.confusion, self.agree)


class SearchImages:
    """D1, kept for the search: each held-out batch's pixels prepared for the fused count pass
    (a seeded ``share`` of each image's labelled pixels), and the whole images where a
    constraint needs label maps."""

    def __init__(self) -> None:
        self.inputs: list = []
        self.whole: list[tuple] = []

    @classmethod
    def of(
        cls, context: Context, n1: int, share: float, req: Requirements, seed: int
    ) -> SearchImages:
        found, first = cls(), 0
        with torch.inference_mode():
            for seen in context.held_out_seen("design: search images (D1)"):
                keep = d1_images(first, len(seen.probs), n1)
                if keep:
                    found.add(seen, keep, share, req.label_maps, pixel_seeds(seed, first, keep))
                first += len(seen.probs)
        return found

    def add(self, seen: Seen, keep: int, share: float, whole: bool, seeds: list[int]) -> None:
        """The first ``keep`` images of a held-out batch (the whole images too with ``whole``)."""
        labels = seen.batch.labels[:keep]
        roi = None if seen.roi is None else seen.roi.expand_as(labels)
        self.add_pixels(seen.probs[:keep], labels, roi, share, seeds)
        if whole:
            ids = None if seen.batch.instances is None else seen.batch.instances[:keep]
            self.whole.append((seen.probs[:keep], seen.batch.labels[:keep], seen.roi, ids))

    def add_pixels(self, probs, labels, roi, share: float, seeds: list[int]) -> None:
        """(B, N, H, W) ``probs``, (B, H, W) ``labels`` and RoIs of B search images: a share of
        each image's labelled pixels (drawn with its seed of :func:`pixel_seeds`), prepared."""
        probs = probs.float()
        if share < 1:
            part = subsample(probs, labels, roi, share=share, seed=seeds)
            probs, labels, roi = part.probs, part.labels, part.roi
        self.inputs.append(prepare_counts(probs, labels, roi))

    def scorer(
        self, req: Requirements, keep_losses: Callable[[np.ndarray], None]
    ) -> Callable[[torch.Tensor], tuple[np.ndarray, float]]:
        """``matrix → (D1 risks (K,), objective)``; each candidate's (n1, K) per-image losses
        go to ``keep_losses``, in the order the search scores them."""

        def score(matrix: torch.Tensor) -> tuple[np.ndarray, float]:
            losses, pooled = [], Pooled()
            for i, inputs in enumerate(self.inputs):
                counts = count_decisions(inputs, matrix)
                losses.append(image_losses(req, counts, matrix, *self.whole[i : i + 1]))
                pooled.add(counts)
            per_image = torch.cat(losses).numpy()
            keep_losses(per_image)
            return defined_risks(per_image)[0], pooled.value(req)

        return score


def image_losses(req: Requirements, counts, matrix, whole=None) -> torch.Tensor:
    """(B, K) per-image constraint losses from a batch's decision ``counts`` (and, where a
    constraint counts segments or instances, ``whole``: the batch's probabilities, labels,
    RoIs and instance ids, decided again under ``matrix``)."""
    if whole is None:
        return req.losses(counts.confusion)
    probs, labels, roi, ids = whole
    return req.losses(counts.confusion, decide(probs, matrix), labels, roi, ids)


def _front(losses_d1: np.ndarray, objective, req: Requirements, delta: float) -> np.ndarray:
    """The D1 Pareto front (candidate indices) of Pareto Testing, before D2 is seen."""
    untested = np.full((1, *losses_d1.shape[1:]), np.nan)
    return pareto_testing(losses_d1, untested, req.alphas, delta, objective, req.maximize).front


def _test_fronts(context: Context, n1: int, req: Requirements, searches) -> list[tuple]:
    """One pass over the held-out images at every pixel for the front of each search: the
    (n2, L, K) D2 losses (NaN off the front) and the (L,) objective on all held-out images
    (NaN off the front)."""
    n2 = len(context.held_out) - n1
    out = []
    for candidates, front in searches:
        length, k = len(candidates.objective), len(req.alphas)
        out.append((np.full((n2, length, k), np.nan), {int(c): Pooled() for c in front}))
    first = 0
    with torch.inference_mode():
        for seen in context.held_out_seen("design: certify (D2)"):
            labels = seen.batch.labels
            roi = None if seen.roi is None else seen.roi.expand_as(labels)
            inputs = prepare_counts(seen.probs.float(), labels, roi)
            in_d1 = d1_images(first, len(labels), n1)
            rows = slice(first + in_d1 - n1, first + len(labels) - n1)  # D2's, in D2's order
            whole = (seen.probs, labels, seen.roi, seen.batch.instances) if req.label_maps else None
            for (candidates, _), (losses_d2, pooled) in zip(searches, out, strict=True):
                for c, counted in pooled.items():
                    matrix = candidates.matrices[c]
                    counts = count_decisions(inputs, matrix)
                    counted.add(counts)
                    if in_d1 < len(labels):
                        losses = image_losses(req, counts, matrix, whole)
                        losses_d2[rows, c] = losses[in_d1:].numpy()
            first += len(labels)
    results = []
    for (candidates, _), (losses_d2, pooled) in zip(searches, out, strict=True):
        objective = np.full(len(candidates.objective), np.nan)
        for c, counted in pooled.items():
            objective[c] = counted.value(req)
        results.append((losses_d2, objective))
    return results


def designed_group(outcome: DesignOutcome) -> RuleGroup | None:
    """The certified designed matrix and the best certified triangle point as one rule group
    (measured on the reported images like every other), or None when neither exists."""
    rules = [
        Rule(found.rule_name, found.candidates.matrices[found.chosen])
        for found in outcome.searches
        if found.chosen is not None
    ]
    if not rules:
        return None
    defer = any(r.defers for r in rules)
    return RuleGroup(
        DESIGNED_FAMILY,
        [r.name for r in rules],
        NamedRules(tuple(rules)),
        [rule_columns(r, defer) for r in rules],
        masks=True,
        rules=rules,
        output=DESIGNED_FAMILY,
        note=f"designed in the {outcome.searches[0].candidates.space} space for "
        f"{', '.join(outcome.requirements.texts)} at δ = {outcome.delta}",
    )


ANALYSIS = Design
