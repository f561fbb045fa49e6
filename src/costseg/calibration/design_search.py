"""The search over a design space on D1 (docs/definitions.md §20): every candidate it scores.

A ``score(matrix) -> (risks (K,), objective)`` callable measures a full cost matrix on D1's
images. Grid spaces (:class:`~costseg.rules.design_spaces.TriangleSpace`,
:class:`~costseg.rules.design_spaces.LagrangianSpace`) score every grid point; the aggregate space
(:class:`~costseg.rules.design_spaces.AggregateSpace`) is searched by Optuna's NSGA-II sampler
over its log-scale box, minimising the K risks and optimising the objective, with ``R_i ≤ α_i``
as constraints (constrained domination), for a budget of candidates and a seed. NSGA-II rather
than multi-objective TPE: its cost per candidate stays flat as the budget and the K + 1
objectives grow (TPE's grows with every trial), it takes the α's as constraints directly, and a
seed makes it reproducible. The returned candidates then go to
:func:`~costseg.calibration.pareto_testing.pareto_testing`, which keeps D1's Pareto front.

Pure: no models, no Lightning; Optuna is imported only by :func:`search_aggregate`.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
import torch
from numpy.typing import ArrayLike, NDArray

from costseg.rules.design_spaces import AggregateSpace, LagrangianSpace, TriangleSpace

Score = Callable[[torch.Tensor], tuple[ArrayLike, float]]
"""``score(matrix (R, N)) -> (risks (K,), objective)`` on D1; a risk is NaN where undefined."""


@dataclass(frozen=True)
class Candidates:
    """Every candidate a search scored, in evaluation order.

    Attributes:
        space: The space's name (``triangle``, ``lagrangian``, ``aggregate``).
        names: (D,) the parameters' names.
        parameters: (L, D) float64 parameter values.
        matrices: (L, R, N) float64 cost matrices (R = N, or N + 1 with a defer row).
        objective: (L,) float64 D1 objective.
    """

    space: str
    names: tuple[str, ...]
    parameters: NDArray[np.float64]
    matrices: torch.Tensor
    objective: NDArray[np.float64]


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
    return _collect(space, [(p.tolist(), space.matrix(p)) for p in points], score)


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
    scored: list[float] = []
    worst = -1e300 if maximize else 1e300  # finite: NSGA-II's crowding distance subtracts

    def objective(trial) -> list[float]:
        values = [trial.suggest_float(name, lo, hi, log=True) for name, lo, hi in box]
        matrix = space.matrix(values)
        risks, value = score(matrix)
        risks = np.asarray(risks, dtype=np.float64).reshape(-1)
        if len(risks) != len(levels):
            raise ValueError(f"score gave {len(risks)} risks for {len(levels)} alphas")
        found.append((values, matrix))
        scored.append(float(value))
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
    return _collect(space, found, score, scored)


def search(
    space: TriangleSpace | LagrangianSpace | AggregateSpace,
    score: Score,
    alphas: Sequence[float],
    budget: int = 500,
    seed: int = 0,
    maximize: bool = True,
) -> Candidates:
    """Every grid point of a grid space (:func:`search_grid`; ``budget`` and ``seed`` unused), or
    ``budget`` candidates of the aggregate space (:func:`search_aggregate`).

    >>> from costseg.rules.triangle import vertex_matrices
    >>> from costseg.rules.design_spaces import TriangleSpace
    >>> space = TriangleSpace(vertex_matrices(["robotistic", "altruistic", "egoistic"]), 0.5)
    >>> search(space, lambda C: ([0.0], 1.0), [0.1]).parameters.shape
    (6, 3)
    """
    if isinstance(space, AggregateSpace):
        return search_aggregate(space, score, alphas, budget, seed, maximize)
    return search_grid(space, score)


def _collect(
    space, found: list[tuple[list[float], torch.Tensor]], score: Score, scored=None
) -> Candidates:
    """The candidates as arrays; ``scored`` holds their objective values when already scored."""
    if scored is None:
        scored = [score(matrix)[1] for _, matrix in found]
    return Candidates(
        space.name,
        tuple(space.parameters),
        np.array([values for values, _ in found], dtype=np.float64).reshape(len(found), -1),
        torch.stack([matrix for _, matrix in found]),
        np.array([float(v) for v in scored], dtype=np.float64),
    )
