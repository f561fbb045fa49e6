"""``--design SPACE``: a cost matrix designed from several requirements and certified by Pareto
Testing on the held-out images (docs/definitions.md §20).

The held-out images split at random in two halves (seeded by ``--seed``:
:func:`~costseg.calibration.pareto_testing.split_images`). D1 is searched: every candidate of the
space scored by one fused decide-and-count pass on every pixel that can change a constraint's
per-image loss under some candidate, and on a seeded share of each image's labelled pixels for the
objective (:mod:`costseg.calibration.search_pixels`), so D1's constraint losses are those of every
pixel. D2 tests the D1 Pareto front in order on every pixel. The certified matrix best by the
objective on all held-out images, and the best certified matrix of each space searched beside
it (the triangle; for ``--design regional``, a stack of matrices decided with the RoI map, also
the whole-image Lagrangian space), join the rule groups, so the reported images measure them
with every usual row; their per-image constraint losses there (what the certificate is about)
are kept beside the pooled rates.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import numpy as np
import torch

from costseg.calibration.design_search import GRID_VALUES, grid_size, search
from costseg.calibration.guarantee import defined_risks
from costseg.calibration.pareto_testing import choose, pareto_testing, split_images
from costseg.calibration.search_pixels import constraint_pixels, gather_pixels
from costseg.classes import CLASS_NAMES, IGNORE_INDEX
from costseg.costs import cost_or_symmetric, is_regional
from costseg.decision import (
    CountInputs,
    DecisionCounts,
    count_decisions,
    decide,
    prepare_counts,
    subsample,
)
from costseg.evaluation.analyses import Analysis, Context, Provided, Seen
from costseg.evaluation.processes import in_image_order
from costseg.evaluation.settings import DesignSettings
from costseg.metrics.per_image import per_image_counts, per_image_loss
from costseg.metrics.requirements import Requirements
from costseg.report.design import DESIGNED_FAMILY, DesignOutcome, SearchOutcome, Split
from costseg.rules import Rule, RuleGroup, parse_rules, vertex_matrices
from costseg.rules.base import needs_roi
from costseg.rules.design_spaces import (
    AggregateSpace,
    Hull,
    LagrangianSpace,
    RegionalHull,
    RegionalLagrangianSpace,
    TriangleSpace,
    aggregate_template,
    defer_directions,
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

    def start(self) -> None:
        """The rule groups whose per-image constraint losses the reported images measure: the
        named rules and the designed ones."""
        groups = self.context.groups
        self.measured = [i for i, g in enumerate(groups) if g.is_named]
        self.measured += [i for i, g in enumerate(groups) if g.family == DESIGNED_FAMILY]
        self.losses: list = []  # (position, (rules, K) per-image losses) of this process

    def process(self, seen: Seen) -> None:
        req, rows = self.outcome.requirements, []
        for index in self.measured:
            preds = seen.preds[index]
            losses = [
                per_image_loss(
                    per_image_counts(
                        preds,
                        seen.batch.labels,
                        seen.roi,
                        t.cls,
                        t.roi,
                        t.metric,
                        instances=seen.batch.instances,
                    ).cpu(),
                    t.metric,
                )
                for t in req.constraints
            ]
            rows.append(torch.stack(losses, -1))  # (B, rules, K)
        losses = torch.cat(rows, 1).double().numpy()
        self.losses += list(zip(seen.positions, losses, strict=True))

    def gather(self) -> None:
        self.losses = in_image_order(self.losses)  # summed in one order, however many processes

    def result(self) -> DesignOutcome:
        names = [n for i in self.measured for n in self.context.groups[i].names]
        req = self.outcome.requirements
        losses = (
            np.stack(self.losses) if self.losses else np.empty((0, len(names), len(req.alphas)))
        )
        risks, images = defined_risks(losses)  # (rules, K)
        above = (losses > np.array(req.alphas)).sum(0)  # NaN compares False
        self.outcome.per_image = {
            text: {
                name: {
                    "risk": None if images[r, i] == 0 else float(risks[r, i]),
                    "images": int(images[r, i]),
                    "above_alpha": int(above[r, i]),
                }
                for r, name in enumerate(names)
            }
            for i, text in enumerate(req.texts)
        }
        return self.outcome


def design(context: Context, settings: DesignSettings) -> DesignOutcome:
    """Search every space of :func:`spaces` on D1, certify each one's Pareto front on D2."""
    req = Requirements.parse(settings.requirements, settings.maximize, settings.minimize)
    delta, seed = settings.delta, settings.seed
    d1, d2 = split_images(len(context.held_out), seed)
    share = 1.0 if req.label_maps else settings.pixels
    searched_spaces = spaces(settings, req)
    found = SearchImages.of(context, d1, share, req, [s.hull() for s in searched_spaces], seed)
    searched = []  # (candidates, their (n1, L, K) per-image losses on D1)
    for space in searched_spaces:
        losses: list[np.ndarray] = []
        candidates = search(
            space, found.scorer(req, losses.append), req.alphas, settings.budget, seed,
            req.maximize, continuous=continuous(space, settings), delta=delta,
        )  # fmt: skip
        searched.append((candidates, np.stack(losses, 1)))
    fronts = [_front(losses, c.objective, req, delta) for c, losses in searched]
    pairs = [(c, f) for (c, _), f in zip(searched, fronts, strict=True)]
    tested = _test_fronts(context, d2, req, pairs)
    outcomes = []
    for i, ((candidates, losses_d1), (losses_d2, pooled)) in enumerate(
        zip(searched, tested, strict=True)
    ):
        objective_all = np.array([np.nan if p is None else p.value(req) for p in pooled])
        result = pareto_testing(
            losses_d1, losses_d2, req.alphas, delta, candidates.objective, req.maximize
        )
        chosen = choose(result, objective_all, req.maximize)
        shown = chosen if chosen is not None else result.best
        defers = candidates.matrices.shape[-2] > candidates.matrices.shape[-1]
        deferred, changed = None, None
        if shown is not None and pooled[shown] is not None:
            deferred = pooled[shown].deferred(req) if defers else None
            changed = pooled[shown].changed()
        outcomes.append(SearchOutcome(candidates, result, chosen, objective_all, designed=i == 0,
                                      deferred=deferred, changed=changed))  # fmt: skip
    split = Split(seed, d1.tolist(), d2.tolist(), found.stems, settings.held_out)
    return DesignOutcome(req, delta, split, share, outcomes, roi=settings.roi,
                         defer=settings.defer)  # fmt: skip


def spaces(settings: DesignSettings, req: Requirements) -> list[Space]:
    """The space of ``--design`` and, to compare: the triangle when it is another; for the
    regional space, also the whole-image Lagrangian space (every constraint moving every
    region's matrix)."""
    defer = settings.defer
    budget = settings.budget // max(1, len(defer))
    n = max(1, int((np.sqrt(8 * budget + 1) - 3) / 2))  # (n + 1)(n + 2) / 2 <= budget
    corners = vertex_matrices(list(settings.vertices), settings.vertex_scaling)
    triangle = TriangleSpace(corners, 1 / n, defer)
    if settings.space == "triangle":
        return [triangle]
    if settings.space == "aggregate":
        box = (min(defer), max(defer)) if defer else None
        own = AggregateSpace(aggregate_template(settings.base or "altruistic"), defer_box=box)
        return [own, triangle]
    base = parse_rules([settings.base or "robotistic"])[0]
    pairs = [(t.cls, t.metric) for t in req.constraints]
    n = len(CLASS_NAMES)
    base_cost = cost_or_symmetric(base.cost, n)
    common = {
        "directions": lagrangian_directions(pairs, n),
        "size": grid_size(settings.budget, len(pairs), len(defer)),
        "defer_costs": defer,
        "deferring": defer_directions(pairs, n),
    }
    if is_regional(base_cost):  # a regional C₀: the whole-image space moves every region
        whole = RegionalLagrangianSpace(base_cost, **common, regions=(0,) * len(pairs),
                                        name="lagrangian")  # fmt: skip
    else:
        whole = LagrangianSpace(base_cost, **common)
    if settings.space == "lagrangian":
        return [whole, triangle]
    regions = tuple(t.roi for t in req.constraints)
    return [RegionalLagrangianSpace(base_cost, **common, regions=regions), whole, triangle]


def continuous(space: Space, settings: DesignSettings) -> bool:
    """Whether the Lagrangian space's multipliers are searched continuously: as
    ``--design_search`` says, else when its grid would be coarse (fewer than
    :data:`~costseg.calibration.design_search.GRID_VALUES` values per multiplier)."""
    if not isinstance(space, LagrangianSpace):
        return False
    if settings.search is not None:
        return settings.search == "continuous"
    return space.size < GRID_VALUES


def pixel_seeds(seed: int, positions: list[int]) -> list[int]:
    """The seeds of the objective's pixel draws of the images at ``positions`` among the
    held-out images: one per image, so any batch size and split draws the same."""
    return [seed + p for p in positions]


class Pooled:
    """One matrix's decision counts pooled over images: the (R + 1, N, N + 1) confusion and the
    pixels decided as argmax, from which the objective is computed (:meth:`Requirements.value`)."""

    def __init__(self) -> None:
        self.confusion, self.agree = 0, 0

    def add(self, counts: DecisionCounts) -> None:
        """Add a batch's counts (:func:`costseg.decision.count_decisions`)."""
        self.confusion = self.confusion + counts.confusion.sum(0)
        self.agree = self.agree + counts.agree.sum()

    def value(self, req: Requirements) -> float:
        return req.value(self.confusion, self.agree)

    def changed(self) -> float | None:
        """The share of labelled pixels decided otherwise than argmax (None: no pixels)."""
        labelled = int(self.confusion[0].sum()) if torch.is_tensor(self.confusion) else 0
        return 1 - int(self.agree) / labelled if labelled else None

    def deferred(self, req: Requirements) -> dict[str, float | None]:
        """The share of labelled pixels deferred: of all, and of each constraint's class in its
        RoI."""
        whole = self.confusion[0].double()
        out = {"all pixels": (whole[:, -1].sum() / whole.sum()).item() if whole.sum() else None}
        for text, t in zip(req.texts, req.constraints, strict=True):
            cell = self.confusion[t.roi].double()
            rows = cell if t.cls is None else cell[t.cls : t.cls + 1]
            out[text] = (rows[:, -1].sum() / rows.sum()).item() if rows.sum() else None
        return out


class Part(NamedTuple):
    """One held-out batch's D1 pixels, prepared once: the first ``images`` rows of the counts
    hold the constraints' pixels; the objective's are the rest (``objective_rows``: all rows
    when the constraints and the objective see the same pixels)."""

    inputs: CountInputs
    images: int
    split: bool

    def constraint_rows(self, counts: DecisionCounts) -> DecisionCounts:
        return DecisionCounts(counts.confusion[: self.images], counts.agree[: self.images])

    def objective_rows(self, counts: DecisionCounts) -> DecisionCounts:
        if not self.split:
            return counts
        return DecisionCounts(counts.confusion[self.images :], counts.agree[self.images :])


class SearchImages:
    """D1, kept for the search: each held-out batch's D1 pixels prepared for the fused count pass
    (the constraints' pixels and the objective's share), the whole images where a constraint
    needs label maps, and the names of every held-out image."""

    def __init__(self) -> None:
        self.parts: list[Part] = []
        self.whole: list[tuple] = []
        self.stems: list[str] = []

    @classmethod
    def of(
        cls,
        context: Context,
        d1: np.ndarray,
        share: float,
        req: Requirements,
        hulls: list[Hull | RegionalHull | None],
        seed: int,
    ) -> SearchImages:
        found, first, searched = cls(), 0, set(d1.tolist())
        with torch.inference_mode():
            for seen in context.held_out_seen("design: search images (D1)"):
                size = len(seen.probs)
                found.stems += list(seen.batch.stems)
                keep = [i for i in range(size) if first + i in searched]
                if keep:
                    seeds = pixel_seeds(seed, [first + i for i in keep])
                    found.add(seen, keep, share, req, hulls, seeds)
                first += size
        return found

    @classmethod
    def of_images(
        cls,
        images: list[tuple],
        share: float,
        req: Requirements,
        hulls: list[Hull | RegionalHull | None],
        seed: int,
    ) -> SearchImages:
        """D1 of batches ``(probs, labels, roi)`` given outright (their images the held-out
        positions 0, 1, …), prepared as :meth:`of` prepares the held-out images."""
        found, first = cls(), 0
        for probs, labels, roi in images:
            seeds = pixel_seeds(seed, list(range(first, first + len(labels))))
            found.add_pixels(probs, labels, roi, share, req, hulls, seeds)
            first += len(labels)
        return found

    def add(
        self, seen: Seen, keep: list[int], share: float, req: Requirements, hulls, seeds
    ) -> None:
        """The images ``keep`` of a held-out batch (the whole images too where needed)."""
        labels = seen.batch.labels[keep]
        roi = None if seen.roi is None else seen.roi.expand_as(seen.batch.labels)[keep]
        self.add_pixels(seen.probs[keep], labels, roi, share, req, hulls, seeds)
        if req.label_maps:
            ids = None if seen.batch.instances is None else seen.batch.instances[keep]
            self.whole.append((seen.probs[keep], labels, roi, ids))

    def add_pixels(
        self,
        probs: torch.Tensor,
        labels: torch.Tensor,
        roi: torch.Tensor | None,
        share: float,
        req: Requirements,
        hulls: list[Hull | RegionalHull | None],
        seeds: list[int],
    ) -> None:
        """(B, N, H, W) ``probs``, (B, H, W) ``labels`` and RoIs of B search images, prepared:
        every pixel that can change a constraint under a candidate of any of the spaces of
        ``hulls`` (:func:`~costseg.calibration.search_pixels.constraint_pixels`) and a ``share``
        of each image's labelled pixels for the objective (drawn with its seed of
        :func:`pixel_seeds`), side by side as 2B images; with ``share`` 1, every pixel once."""
        probs = probs.float()
        if share >= 1:
            self.parts.append(Part(prepare_counts(probs, labels, roi), len(probs), False))
            return
        needs = req.pixel_needs()
        keep = torch.zeros_like(labels, dtype=torch.bool)
        for hull in hulls:
            keep |= constraint_pixels(probs, labels, roi, needs, hull)
        own = gather_pixels(probs, labels, roi, keep)
        drawn = subsample(probs, labels, roi, share=share, seed=seeds)
        size = max(own[0].shape[-1], drawn.probs.shape[-1])

        def padded(values: torch.Tensor, fill: float) -> torch.Tensor:
            return torch.nn.functional.pad(values, (0, size - values.shape[-1]), value=fill)

        both_probs = torch.cat([padded(own[0], 0.0), padded(drawn.probs, 0.0)])
        both_labels = torch.cat([padded(own[1], IGNORE_INDEX), padded(drawn.labels, IGNORE_INDEX)])
        both_roi = None if roi is None else torch.cat([padded(own[2], 0), padded(drawn.roi, 0)])
        self.parts.append(Part(prepare_counts(both_probs, both_labels, both_roi), len(probs), True))

    def scorer(
        self, req: Requirements, keep_losses: Callable[[np.ndarray], None]
    ) -> Callable[[torch.Tensor], tuple[np.ndarray, float, np.ndarray]]:
        """``matrix → (D1 risks (K,), objective, images with a defined loss (K,))``; each
        candidate's (n1, K) per-image losses go to ``keep_losses``, in the order the search
        scores them."""

        def score(matrix: torch.Tensor) -> tuple[np.ndarray, float, np.ndarray]:
            losses, pooled = [], Pooled()
            for i, part in enumerate(self.parts):
                counts = count_decisions(part.inputs, matrix)
                own = part.constraint_rows(counts)
                losses.append(image_losses(req, own, matrix, *self.whole[i : i + 1]))
                pooled.add(part.objective_rows(counts))
            per_image = torch.cat(losses).numpy()
            keep_losses(per_image)
            risks, defined = defined_risks(per_image)
            return risks, pooled.value(req), defined

        return score


def image_losses(req: Requirements, counts, matrix, whole=None) -> torch.Tensor:
    """(B, K) per-image constraint losses from a batch's decision ``counts`` (and, where a
    constraint counts segments or instances, ``whole``: the batch's probabilities, labels,
    RoIs and instance ids, decided again under ``matrix``, a regional stack with the RoIs)."""
    if whole is None:
        return req.losses(counts.confusion)
    probs, labels, roi, ids = whole
    preds = decide(probs, matrix, roi=roi if is_regional(matrix) else None)
    return req.losses(counts.confusion, preds, labels, roi, ids)


def _front(losses_d1: np.ndarray, objective, req: Requirements, delta: float) -> np.ndarray:
    """The D1 Pareto front (candidate indices) of Pareto Testing, before D2 is seen."""
    untested = np.full((1, *losses_d1.shape[1:]), np.nan)
    return pareto_testing(losses_d1, untested, req.alphas, delta, objective, req.maximize).front


def _test_fronts(context: Context, d2: np.ndarray, req: Requirements, searches) -> list[tuple]:
    """One pass over the held-out images at every pixel for the front of each search: the
    (n2, L, K) D2 losses (NaN off the front) and each candidate's counts pooled over all
    held-out images (None off the front)."""
    rows = {int(p): r for r, p in enumerate(d2.tolist())}  # D2's positions → their rows
    out = []
    for candidates, front in searches:
        length, k = len(candidates.objective), len(req.alphas)
        pooled = [None] * length
        for c in front:
            pooled[int(c)] = Pooled()
        out.append((np.full((len(d2), length, k), np.nan), pooled))
    first = 0
    with torch.inference_mode():
        for seen in context.held_out_seen("design: certify (D2)"):
            labels = seen.batch.labels
            roi = None if seen.roi is None else seen.roi.expand_as(labels)
            inputs = prepare_counts(seen.probs.float(), labels, roi)
            mine = [(i, rows[first + i]) for i in range(len(labels)) if first + i in rows]
            whole = (seen.probs, labels, seen.roi, seen.batch.instances) if req.label_maps else None
            for (candidates, _), (losses_d2, pooled) in zip(searches, out, strict=True):
                for c, counted in enumerate(pooled):
                    if counted is None:
                        continue
                    matrix = candidates.matrices[c]
                    counts = count_decisions(inputs, matrix)
                    counted.add(counts)
                    if mine:
                        losses = image_losses(req, counts, matrix, whole).numpy()
                        at, to = zip(*mine, strict=True)
                        losses_d2[list(to), c] = losses[list(at)]
            first += len(labels)
    return out


def designed_group(outcome: DesignOutcome) -> RuleGroup | None:
    """The certified designed matrix and the best certified matrix of each space searched to
    compare, as one rule group (measured on the reported images like every other, shown in
    the headline tables), or None when none exists."""
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
        headline=True,
        needs_roi=needs_roi(rules),
        rules=rules,
        output=DESIGNED_FAMILY,
        note=f"designed in the {outcome.searches[0].candidates.space} space for "
        f"{', '.join(outcome.requirements.texts)} at δ = {outcome.delta}",
    )


ANALYSIS = Design
