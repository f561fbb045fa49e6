"""The shared types of every rule family: a :class:`Rule` and a :class:`RuleGroup`.

A rule family (named rules, the value triangle, the α path, temperatures) is one module of
:mod:`costseg.rules` that builds a :class:`RuleGroup`; the group carries everything the
evaluation and the reports need (its label, its result columns, where its rules lie for figures,
each rule's cost matrix), so any group is evaluated and written without special cases.

A group decides ``decide(probs, priors, roi=None)``: the pixel-wise priors for rules that divide
by them (``ml``), the RoI map for rules that need one (a regional value system,
docs/definitions.md §21); every other group ignores them.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field

import torch

from costseg.costs import has_defer_row, is_regional, mix_costs

Decider = Callable[..., torch.Tensor]
"""``decide(probs (B, N, H, W), priors (N, H, W) or None, roi=(H, W) RoI ids or None)`` →
(B, K, H, W) labels."""

DEFER_COLUMN = "defer"
"""The column of a rule's defer cost in result rows (:attr:`Rule.defer_cost`), beside
``matrix``, in the rows of groups where some rule defers."""


@dataclass(frozen=True)
class Rule:
    """One decision rule.

    Attributes:
        name: shown in tables, files and TensorBoard tags.
        cost: (N, N) float64 matrix, or (N + 1, N) with a defer row (docs/definitions.md §14);
            ``None`` = the symmetric matrix; a regional value system's (R + 1, N, N) or
            (R + 1, N + 1, N) stack, decided with the RoI map (docs/definitions.md §21).
        priors_alpha: 0 = no priors; α in (0, 1] = the rule on ``p / π_α`` with
            ``π_α = (1 - α) + α π`` (1 = maximum likelihood when ``cost`` is None).
    """

    name: str
    cost: torch.Tensor | None
    priors_alpha: float = 0.0

    @property
    def defers(self) -> bool:
        """Whether the rule may defer a pixel (its matrix has a defer row)."""
        return self.cost is not None and has_defer_row(self.cost)

    @property
    def regional(self) -> bool:
        """Whether the rule is a regional value system (a matrix per RoI, decided with the RoI
        map: docs/definitions.md §21)."""
        return is_regional(self.cost)

    @property
    def defer_cost(self) -> float | list | None:
        """The rule's cost of deferring: one number when it is the same for every true class
        (and region), else one per class (a regional rule whose regions' rows differ: one list
        per region, the default first); None when the rule never defers.

        >>> from costseg.costs import with_defer
        >>> Rule("a", with_defer(torch.ones(2, 2), 0.25)).defer_cost, Rule("b", None).defer_cost
        (0.25, None)
        """
        if not self.defers:
            return None
        rows = (self.cost[:, -1] if self.regional else self.cost[-1:]).tolist()
        if len({v for row in rows for v in row}) == 1:
            return rows[0][0]
        return rows[0] if all(row == rows[0] for row in rows) else rows


def needs_priors(rules: Iterable[Rule]) -> bool:
    """Whether one of ``rules`` divides by the pixel-wise priors (``ml``, a prior-adapted rule).

    >>> needs_priors([Rule("a", None), Rule("ml", None, 1.0)]), needs_priors([Rule("a", None)])
    (True, False)
    """
    return any(r.priors_alpha for r in rules)


def needs_roi(rules: Iterable[Rule]) -> bool:
    """Whether one of ``rules`` is a regional value system, decided with the RoI map.

    >>> needs_roi([Rule("a", torch.ones(5, 2, 2) - torch.eye(2))]), needs_roi([Rule("a", None)])
    (True, False)
    """
    return any(r.regional for r in rules)


def plain_rules(rules: Sequence[Rule], what: str) -> Sequence[Rule]:
    """``rules``; ValueError naming the first regional one, where ``what`` takes one matrix.

    >>> plain_rules([Rule("a", torch.ones(5, 2, 2) - torch.eye(2))], "--vertices")
    Traceback (most recent call last):
    ...
    ValueError: --vertices takes one matrix; a is a regional value system (a matrix per RoI)
    """
    for rule in rules:
        if rule.regional:
            raise ValueError(
                f"{what} takes one matrix; {rule.name} is a regional value system (a matrix "
                "per RoI)"
            )
    return rules


def given_priors(priors: torch.Tensor | None, what: str) -> torch.Tensor:
    """``priors``, which ``what`` (a rule, the α sweep) divides by; ValueError when there are
    none."""
    if priors is None:
        raise ValueError(f"{what} needs pixel-wise priors")
    return priors


def adapted_priors(priors: torch.Tensor, alpha: float) -> torch.Tensor:
    """Bayes ↔ ML interpolation (docs/definitions.md §1): ``π_α = (1 - α)·1 + α·π``.

    >>> adapted_priors(torch.tensor([0.2, 0.8], dtype=torch.float64), 0.5).tolist()
    [0.6, 0.9]
    """
    return (1 - alpha) + alpha * priors


@dataclass
class RuleGroup:
    """K rules decided together: ``decide(probs (B,N,H,W), priors) → (B, K, H, W)``.

    Attributes:
        family: the family's label (``rules``, ``grid``, ``alpha``, ``temperature``), for
            messages and TensorBoard tags.
        names: the K rule names.
        decide: the decision function.
        columns: per rule, the columns that identify it in result rows.
        is_named: the rules named by ``--cost``: the headline tables, masks and saved label maps.
        masks: whether its rules join the named ones in the example mask figures.
        headline: whether its rules join the named ones in the headline tables (table.md's
            main and mIoU tables, the console's).
        heatmaps: whether FP/FN location maps are kept (off for sweeps of many rules).
        needs_priors: whether some rule divides by the pixel-wise priors.
        needs_roi: whether some rule is a regional value system, decided with the RoI map.
        candidates: whether ``--target`` and ``--guarantee`` choose among its rules.
        output: file stem of its own result rows and figures (``sweep`` → ``sweep.csv``), or
            None when it is written with the headline results or elsewhere.
        rules: the group's rules where each is a named rule (named, temperature and defer-sweep
            groups); :attr:`defers` whether one of them may defer a pixel (docs/definitions.md
            §14).
        vertices: (3, N, N) vertex matrices, ``weights`` (K, 3) and ``corners`` (3 names) of
            rules that lie in the value triangle (drawn as triangles).
        line: (K,) positions of rules that lie along one axis (drawn as curves), ``axis`` its
            label.
        paths: the orders in which fixed-sequence testing (``--guarantee_method
            fixed_sequence``) walks the rules, one path per named rule of the defer sweep (from
            its smallest defer cost up), Bonferroni over the paths; empty: one path, the group's
            order.
        prefer: (K,) among rules with the same best ``--maximize`` value, ``--target`` and
            ``--guarantee`` take the one of largest ``prefer`` (the defer sweep: its defer cost);
            None: the first.
        note: how the group was built, for every output that shows it.
        temperature: decide on ``softmax(z / T)`` of the raw logits instead of the
            probabilities every other group sees (the temperature sweep, docs/definitions.md §6).
    """

    family: str
    names: list[str]
    decide: Decider
    columns: list[dict[str, object]]
    is_named: bool = False
    masks: bool = False
    headline: bool = False
    heatmaps: bool = False
    needs_priors: bool = False
    needs_roi: bool = False
    candidates: bool = False
    output: str | None = None
    rules: list[Rule] = field(default_factory=list)
    vertices: torch.Tensor | None = None
    weights: torch.Tensor | None = None
    corners: tuple[str, ...] = ()
    line: tuple[float, ...] | None = None
    axis: str = ""
    paths: tuple[tuple[int, ...], ...] = ()
    prefer: tuple[float, ...] | None = None
    note: str = ""
    temperature: float | None = None

    @property
    def defers(self) -> bool:
        """Whether a rule of the group may defer a pixel: its results have the defer columns."""
        return any(r.defers for r in self.rules)

    def cost(self, k: int) -> torch.Tensor | None:
        """The (N, N) (or (N + 1, N), with a defer row) cost matrix of rule k (a regional
        value system: its stack), or None when the rule is no plain matrix (it uses the priors,
        or is the symmetric matrix of argmax)."""
        if self.vertices is not None and self.weights is not None:
            return mix_costs(self.vertices, self.weights[k : k + 1])[0]
        if self.rules and not self.rules[k].priors_alpha:
            return self.rules[k].cost
        return None


def require_priors(groups: Sequence[RuleGroup], priors: torch.Tensor | None) -> None:
    """ValueError if a rule of ``groups`` divides by pixel-wise priors (``ml``, the α sweep)
    and there are none."""
    needing = dict.fromkeys(
        "--alpha_sweep" if g.family == "alpha" else "the rule ml" for g in groups if g.needs_priors
    )
    if priors is None and needing:
        verb = "need" if len(needing) > 1 else "needs"
        raise ValueError(
            f"{' and '.join(needing)} {verb} pixel-wise priors, and there are none for these "
            "images: pass --priors FILE (a run's priors.pt, or scripts/count_priors.py's)"
        )


def require_roi(
    groups: Sequence[RuleGroup],
    roi: torch.Tensor | None,
    how: str = "give the images priors or the geometric RoI map",
) -> None:
    """ValueError if a rule of ``groups`` is a regional value system and there is no RoI map
    (``roi`` None: no priors and no geometric map); ``how`` says what to give (the command's
    options).

    >>> require_roi([RuleGroup("r", ["s"], None, [], rules=[Rule("s", torch.ones(5, 2, 2))],
    ...                        needs_roi=True)], None)  # doctest: +ELLIPSIS
    Traceback (most recent call last):
    ...
    ValueError: s decides each RoI with its own matrix and needs a RoI map, and there is none ...
    """
    needing = dict.fromkeys(r.name for g in groups if g.needs_roi for r in g.rules if r.regional)
    if roi is None and needing:
        raise ValueError(
            f"{', '.join(needing)} decides each RoI with its own matrix and needs a RoI map, and "
            f"there is none for these images: {how} (docs/definitions.md §3)"
        )


def named_group(groups: Sequence[RuleGroup]) -> RuleGroup:
    """The group of the named rules (``--cost``) among ``groups``."""
    return next(g for g in groups if g.is_named)


def masked_groups(groups: Sequence[RuleGroup]) -> list[RuleGroup]:
    """The groups whose rules the example mask figures show: the named rules, then every group
    with :attr:`RuleGroup.masks`."""
    return [named_group(groups)] + [g for g in groups if g.masks and not g.is_named]
