"""The search over a design space on D1 (docs/definitions.md §20): every candidate it scores.

A ``score(matrix) -> (risks (K,), objective[, defined (K,)])`` callable measures a full cost
matrix on D1's images (``defined``: the images with a defined loss behind each risk). Grid spaces
(:class:`~costseg.rules.design_spaces.TriangleSpace`,
:class:`~costseg.rules.design_spaces.LagrangianSpace`) score every grid point; the Lagrangian
space may instead be searched continuously (:func:`search_multipliers`: Optuna's TPE sampler
over log μ, steered to the matrices D1 alone would certify); the aggregate space
(:class:`~costseg.rules.design_spaces.AggregateSpace`) is searched by Optuna's NSGA-II sampler
over its log-scale box, minimising the K risks and optimising the objective, with ``R_i ≤ α_i``
as constraints (constrained domination), for a budget of candidates and a seed. NSGA-II rather
than multi-objective TPE: its cost per candidate stays flat as the budget and the K + 1
objectives grow (TPE's grows with every trial), it takes the α's as constraints directly, and a
seed makes it reproducible. The returned candidates then go to
:func:`~costseg.calibration.pareto_testing.pareto_testing`, which keeps D1's Pareto front.

Pure: no models, no Lightning; Optuna is imported only by the searches that use it.
"""

from __future__ import annotations

import itertools
import math
import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
import torch
from numpy.typing import NDArray

from costseg.calibration.guarantee import hoeffding_bentkus_pvalue
from costseg.rules.design_spaces import AggregateSpace, LagrangianSpace, TriangleSpace

Score = Callable[[torch.Tensor], tuple]
"""``score(matrix (R, N)) -> (risks (K,), objective)`` on D1, or ``(risks, objective, defined)``
with the (K,) numbers of images with a defined loss behind each risk; a risk is NaN where
undefined."""

GRID_VALUES = 8
"""The fewest values per multiplier at which ``--design lagrangian`` searches a grid by default;
a coarser grid gives way to :func:`search_multipliers`."""


@dataclass(frozen=True)
class Candidates:
    """Every candidate a search scored, in evaluation order.

    Attributes:
        space: The space's name (``triangle``, ``lagrangian``, ``aggregate``).
        names: (D,) the parameters' names.
        parameters: (L, D) float64 parameter values.
        matrices: (L, R, N) float64 cost matrices (R = N, or N + 1 with a defer row).
        objective: (L,) float64 D1 objective.
        how: how the space was searched, in words.
    """

    space: str
    names: tuple[str, ...]
    parameters: NDArray[np.float64]
    matrices: torch.Tensor
    objective: NDArray[np.float64]
    how: str = "every grid point"


def search_grid(space: TriangleSpace | LagrangianSpace, score: Score) -> Candidates:
    """Score every point of a grid space, in the grid's order.

    >>> from costseg.costs import symmetric_cost
    >>> from costseg.rules.design_spaces import lagrangian_directions
    >>> space = LagrangianSpace(symmetric_cost(2), lagrangian_directions([(1, "recall")], 2), 3)
    >>> found = search_grid(space, lambda C: ([1 / (1 + C[0, 1].item())], C[0, 1].item()))
    >>> found.parameters[:, 0].tolist(), found.objective.tolist()
    ([0.0, 0.01, 100.0], [1.0, 1.01, 101.0])
    """
    points = space.grid()
    found = _collect(space, [(p.tolist(), space.matrix(p)) for p in points], score)
    if isinstance(space, LagrangianSpace):
        return _described(found, f"a grid of {space.size} values per multiplier (0 and "
                                 f"{space.low:g} … {space.high:g})")  # fmt: skip
    return _described(found, f"a barycentric grid of step {space.step:g}")


def grid_size(budget: int, multipliers: int, defer_costs: int = 0) -> int:
    """Values per multiplier of the finest Lagrangian grid within ``budget`` candidates (at
    least 2), each grid point tried at every defer cost.

    >>> grid_size(300, 2), grid_size(300, 3), grid_size(300, 3, defer_costs=2)
    (17, 6, 5)
    """
    return max(2, int((budget // max(1, defer_costs)) ** (1 / multipliers) + 1e-9))


def search_multipliers(
    space: LagrangianSpace,
    score: Score,
    alphas: Sequence[float],
    budget: int,
    seed: int = 0,
    maximize: bool = True,
    delta: float | None = None,
) -> Candidates:
    """Search the multipliers of the Lagrangian space continuously: Optuna's TPE sampler over
    ``log μ_i ∈ [log low, log high]`` (and, with defer costs, one of them per candidate), for
    ``budget`` candidates, the same for a seed.

    The first candidates are μ = 0 (the base matrix) and the corners of the box, the one with
    every μ_i = high first (the most cautious matrix: the front always holds it), at each defer
    cost, as many as the budget allows. The sampler then maximises (or minimises) the objective
    under constraints: with δ and a ``score`` that gives the images behind each risk, that D1's
    Hoeffding–Bentkus p-value of every ``H_i: R_i > α_i`` is at most δ (the matrices D1 alone
    would certify, where the certified choice lies); else ``R_i ≤ α_i``. A NaN objective counts
    as the worst value, a NaN risk as 1. The candidates then go to Pareto Testing as any others.

    >>> from costseg.costs import symmetric_cost
    >>> from costseg.rules.design_spaces import lagrangian_directions
    >>> space = LagrangianSpace(symmetric_cost(2), lagrangian_directions([(1, "recall")], 2))
    >>> found = search_multipliers(space, lambda C: ([1 / C[0, 1].item()], C[0, 1].item()),
    ...                            [0.5], 5)
    >>> found.parameters[:2, 0].tolist(), found.objective[:2].tolist()
    ([0.0, 100.0], [1.0, 101.0])
    """
    import optuna  # ~1 s to import: only for this search

    levels = np.array([float(a) for a in alphas])
    k = len(space.directions)
    if budget < 1 or len(levels) != k:
        raise ValueError(f"need budget >= 1 and one alpha per multiplier ({k}); got {budget}, "
                         f"{levels.tolist()}")  # fmt: skip
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    defers = list(space.defer_costs) or [None]
    found: list[tuple[list[float], torch.Tensor]] = []
    scored: list[tuple] = []

    def point(mu: Sequence[float], defer: float | None) -> list[float]:
        return [*mu, *([] if defer is None else [defer])]

    def measure(values: list[float]) -> tuple[NDArray[np.float64], float, NDArray | None]:
        matrix = space.matrix(values)
        result = score(matrix)
        risks = np.asarray(result[0], dtype=np.float64).reshape(-1)
        if len(risks) != k:
            raise ValueError(f"score gave {len(risks)} risks for {k} alphas")
        found.append((values, matrix))
        scored.append((risks, float(result[1])))
        return risks, float(result[1]), (np.asarray(result[2]) if len(result) > 2 else None)

    corners = sorted(itertools.product((space.low, space.high), repeat=k), key=lambda c: -sum(c))
    anchors = [point([0.0] * k, d) for d in defers] + [point(c, d) for c in corners for d in defers]
    for values in anchors[: min(len(defers), budget)]:  # μ = 0 lies outside the sampler's box
        measure(values)
    sampler_anchors = anchors[len(defers) : budget]
    trials = budget - len(found)
    if trials <= 0:
        return _described(_collect(space, found, score, scored), "the box's corners")
    worst = -1e300 if maximize else 1e300
    names = space.parameters

    def objective(trial) -> float:
        mu = [trial.suggest_float(n, space.low, space.high, log=True) for n in names[:k]]
        defer = trial.suggest_categorical("defer", defers) if space.defer_costs else None
        risks, value, defined = measure(point(mu, defer))
        filled = np.where(np.isnan(risks), 1.0, risks)
        if delta is not None and defined is not None:
            excess = (
                np.array(
                    [
                        hoeffding_bentkus_pvalue(r, n, a).item()
                        for r, n, a in zip(filled, defined, levels, strict=True)
                    ]
                )
                - delta
            )
        else:
            excess = filled - levels  # fmt: skip
        for i, e in enumerate(excess.tolist()):
            trial.set_constraint(f"risk_{i + 1}", e)  # feasible where <= 0
        return worst if math.isnan(value) else value

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", optuna.exceptions.ExperimentalWarning)
        sampler = optuna.samplers.TPESampler(seed=seed, multivariate=True)
    study = optuna.create_study(direction="maximize" if maximize else "minimize", sampler=sampler)
    for values in sampler_anchors:
        study.enqueue_trial(dict(zip(names, values, strict=True)))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", optuna.exceptions.ExperimentalWarning)
        study.optimize(objective, n_trials=trials)
    steer = "D1's p-values <= δ" if delta is not None else "R_i <= α_i on D1"
    return _described(
        _collect(space, found, score, scored),
        f"Optuna's TPE sampler over log μ in [{space.low:g}, {space.high:g}] (seed {seed}; "
        f"μ = 0 and the box's corners first; constraints: {steer})",
    )


def search_aggregate(
    space: AggregateSpace,
    score: Score,
    alphas: Sequence[float],
    budget: int,
    seed: int = 0,
    maximize: bool = True,
    start: bool = True,
    population: int = 50,
) -> Candidates:
    """Search the aggregate space with Optuna's NSGA-II sampler: ``budget`` candidates, the K
    risks minimised and the objective maximised (or minimised), constrained by ``R_i ≤ α_i``.

    The same ``seed`` gives the same candidates. A NaN risk counts as 1 for the sampler, a NaN
    objective as the worst value; the candidates keep what ``score`` gave.

    Args:
        space: The aggregate space (its box, log scale).
        score: ``matrix -> (risks (K,), objective)`` on D1.
        alphas: (K,) levels α_i of the constraints.
        budget: Candidates to score (≥ 1).
        seed: The sampler's seed.
        maximize: Whether a larger objective is better.
        start: Score the template's own matrix first (its entries clipped to the box).
        population: NSGA-II's population size (≥ 2).

    >>> from costseg.rules.design_spaces import aggregate_template
    >>> space = AggregateSpace(aggregate_template("altruistic"), 1.0, 1000.0)
    >>> found = search_aggregate(space, lambda C: ([C[0, 11].item() / 2000], 0.0), [0.1], 3)
    >>> found.parameters.shape, found.matrices[0, 0, 11].item()  # first: the template itself
    ((3, 30), 1000.0)
    """
    import optuna  # ~1 s to import: only for this search

    levels = [float(a) for a in alphas]
    if budget < 1 or population < 2 or not levels:
        raise ValueError(f"need budget >= 1, population >= 2 and one alpha or more; got "
                         f"{budget}, {population}, {levels}")  # fmt: skip
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    box = space.box()
    found: list[tuple[list[float], torch.Tensor]] = []
    scored: list[tuple[NDArray[np.float64], float]] = []
    worst = -1e300 if maximize else 1e300  # finite: NSGA-II's crowding distance subtracts

    def objective(trial) -> list[float]:
        values = [trial.suggest_float(name, lo, hi, log=True) for name, lo, hi in box]
        matrix = space.matrix(values)
        risks, value = score(matrix)[:2]
        risks = np.asarray(risks, dtype=np.float64).reshape(-1)
        if len(risks) != len(levels):
            raise ValueError(f"score gave {len(risks)} risks for {len(levels)} alphas")
        found.append((values, matrix))
        scored.append((risks, float(value)))
        filled = np.where(np.isnan(risks), 1.0, risks)
        for i, excess in enumerate((filled - np.array(levels)).tolist()):
            trial.set_constraint(f"risk_{i + 1}", excess)  # feasible where <= 0
        return [*filled.tolist(), worst if math.isnan(value) else float(value)]

    study = optuna.create_study(
        directions=["minimize"] * len(levels) + ["maximize" if maximize else "minimize"],
        sampler=optuna.samplers.NSGAIISampler(population_size=population, seed=seed),
    )
    if start:
        entries = space.template.entries().tolist()
        first = {
            name: min(max(v, lo), hi)
            for (name, lo, hi), v in zip(box[: len(entries)], entries, strict=True)
        }
        if space.defer_box is not None:
            first[box[-1][0]] = math.sqrt(box[-1][1] * box[-1][2])  # the box's log middle
        study.enqueue_trial(first)
    study.optimize(objective, n_trials=budget)
    return _described(
        _collect(space, found, score, scored),
        f"Optuna's NSGA-II sampler over the log-scale box (population {population}, seed {seed})",
    )


def search(
    space: TriangleSpace | LagrangianSpace | AggregateSpace,
    score: Score,
    alphas: Sequence[float],
    budget: int = 500,
    seed: int = 0,
    maximize: bool = True,
    continuous: bool = False,
    delta: float | None = None,
) -> Candidates:
    """Every grid point of a grid space (:func:`search_grid`; ``budget`` and ``seed`` unused),
    ``budget`` candidates of the Lagrangian space searched ``continuous``-ly
    (:func:`search_multipliers`, steered by δ), or of the aggregate space
    (:func:`search_aggregate`).

    >>> from costseg.rules.triangle import vertex_matrices
    >>> from costseg.rules.design_spaces import TriangleSpace
    >>> space = TriangleSpace(vertex_matrices(["robotistic", "altruistic", "egoistic"]), 0.5)
    >>> search(space, lambda C: ([0.0], 1.0), [0.1]).parameters.shape
    (6, 3)
    """
    if isinstance(space, AggregateSpace):
        return search_aggregate(space, score, alphas, budget, seed, maximize)
    if continuous and isinstance(space, LagrangianSpace):
        return search_multipliers(space, score, alphas, budget, seed, maximize, delta)
    return search_grid(space, score)


def _described(found: Candidates, how: str) -> Candidates:
    return Candidates(found.space, found.names, found.parameters, found.matrices,
                      found.objective, how)  # fmt: skip


def _collect(
    space, found: list[tuple[list[float], torch.Tensor]], score: Score, scored=None
) -> Candidates:
    """The candidates as arrays; ``scored`` holds their (risks, objective) when already scored."""
    if scored is None:
        scored = [score(matrix)[:2] for _, matrix in found]
    return Candidates(
        space.name,
        tuple(space.parameters),
        np.array([values for values, _ in found], dtype=np.float64).reshape(len(found), -1),
        torch.stack([matrix for _, matrix in found]),
        np.array([float(v) for _, v in scored], dtype=np.float64),
    )
