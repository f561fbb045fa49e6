"""The search spaces of a designed value system: parameters → a full cost matrix
(docs/definitions.md §20).

Each space maps a parameter vector to an (N, N) float64 matrix, or (N + 1, N) when a defer row is
part of it (then the scalar defer cost is the space's last parameter):

* :class:`TriangleSpace`: the mixtures ``α·A + β·B + γ·C`` of three vertices (§2, §7's grid);
* :class:`LagrangianSpace`: ``C(μ) = C₀ + Σ_i μ_i A_i``, one multiplier per constraint, on a
  log-spaced grid of μ (:func:`lagrangian_directions`, :func:`multiplier_grid`);
* :class:`RegionalLagrangianSpace`: the same by region (§21), a stack (R + 1, N(+1), N) of
  matrices ``C_r(μ) = C₀_r + Σ_{i : r_i = r or r_i = 0} μ_i A_i``, decided with the RoI map;
* :class:`AggregateSpace`: the aggregate matrix of §2 with its off-diagonal entries free in a box
  (log scale), expanded to the class matrix by :func:`costseg.costs.expand_aggregates`.

Grid spaces list their points (``grid()``); the aggregate space gives its box (``box()``) to an
optimiser (:mod:`costseg.calibration.design_search`), and so may the Lagrangian space (its
multipliers on a log scale). Each space also bounds its candidates (``hull()``, a :class:`Hull`;
the regional space's a :class:`RegionalHull`, one per RoI; None where no bound is derived): what
lets the search leave out the pixels that no candidate can decide as a constraint's class
(:mod:`costseg.calibration.search_pixels`).

>>> from costseg.costs import symmetric_cost
>>> space = LagrangianSpace(symmetric_cost(3), lagrangian_directions([(2, "recall")], 3), size=3)
>>> space.parameters, space.grid().tolist()
(('mu_1',), [[0.0], [0.01], [100.0]])
>>> space.matrix([100.0])[:, 2].tolist()      # missing class 2 costs 101
[101.0, 101.0, 0.0]
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import torch

from costseg.classes import CLASS_NAMES, NUM_ROIS
from costseg.costs import (
    COSTS_DIR,
    PRESETS,
    barycentric_grid,
    expand_aggregates,
    is_regional,
    mix_costs,
    off_diagonal,
    read_yaml,
    validate_cost,
    with_defer,
)

ConstraintKind = Literal["recall", "precision"]

RECALL_TYPE: tuple[str, ...] = ("recall", "fn_rate", "instance_recall", "handled_recall")
"""Target metrics (names of :mod:`costseg.metrics.names`) that rise when missing the class costs
more: the Lagrangian space raises the class's column."""

PRECISION_TYPE: tuple[str, ...] = ("precision", "fp_rate")
"""Target metrics that improve when calling something the class costs more: the Lagrangian space
raises the class's row."""


def constraint_kind(metric: str) -> ConstraintKind:
    """Whether the Lagrangian space steers ``metric`` through the class's column (``"recall"``)
    or its row (``"precision"``).

    Raises:
        ValueError: a metric neither raising a column nor a row steers in one direction (dice,
            coverage, selective recall: each mixes both kinds of error, or deferrals).

    >>> constraint_kind("fn_rate"), constraint_kind("precision")
    ('recall', 'precision')
    >>> constraint_kind("dice")  # doctest: +ELLIPSIS
    Traceback (most recent call last):
    ...
    ValueError: the Lagrangian design space cannot steer 'dice': ...
    """
    if metric in RECALL_TYPE:
        return "recall"
    if metric in PRECISION_TYPE:
        return "precision"
    raise ValueError(
        f"the Lagrangian design space cannot steer {metric!r}: it takes a recall-type metric "
        f"({', '.join(RECALL_TYPE)}) or a precision-type one ({', '.join(PRECISION_TYPE)})"
    )


def lagrangian_directions(constraints: Sequence[tuple[int, str]], num_classes: int) -> torch.Tensor:
    """The matrices ``A_i`` of the Lagrangian space, one per constraint (docs/definitions.md §20).

    A recall-type constraint on class c has ``A[k, c] = 1`` for every k ≠ c (missing c costs
    more); a precision-type one ``A[c, j] = 1`` for every j ≠ c (calling something c costs more);
    0 elsewhere.

    Args:
        constraints: (class index c, metric name) per constraint, in the order of μ.
        num_classes: N.

    Returns:
        (K, N, N) float64.

    Raises:
        ValueError: a class index outside [0, N) or a metric :func:`constraint_kind` refuses.

    >>> lagrangian_directions([(0, "recall"), (1, "precision")], 3).tolist()
    [[[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [1.0, 0.0, 0.0]], [[0.0, 0.0, 0.0], [1.0, 0.0, 1.0], [0.0, 0.0, 0.0]]]
    """  # noqa: E501
    directions = torch.zeros(len(constraints), num_classes, num_classes, dtype=torch.float64)
    off = 1 - torch.eye(num_classes, dtype=torch.float64)
    for i, (c, metric) in enumerate(constraints):
        kind = constraint_kind(metric)
        if not 0 <= c < num_classes:
            raise ValueError(f"constraint {i + 1}: class index {c} is outside [0, {num_classes})")
        if kind == "recall":
            directions[i, :, c] = off[:, c]
        else:
            directions[i, c, :] = off[c, :]
    return directions


DEFERRAL_IS_HANDLED: tuple[str, ...] = ("handled_recall",)
"""Recall-type metrics that count a deferred pixel of the class as handled, not missed."""


def defer_directions(constraints: Sequence[tuple[int, str]], num_classes: int) -> torch.Tensor:
    """How each constraint's multiplier moves a defer row: a recall-type constraint on class c
    whose rate counts a deferred pixel of c as a miss (recall, FN segments, missed instances)
    raises the row's cost for true class c (deferring c costs more, as missing it does); the
    others (precision-type, handled recall) leave it.

    Returns:
        (K, N) float64.

    >>> defer_directions([(1, "recall"), (1, "handled_recall"), (0, "precision")], 2).tolist()
    [[0.0, 1.0], [0.0, 0.0], [0.0, 0.0]]
    """
    out = torch.zeros(len(constraints), num_classes, dtype=torch.float64)
    for i, (c, metric) in enumerate(constraints):
        if constraint_kind(metric) == "recall" and metric not in DEFERRAL_IS_HANDLED:
            out[i, c] = 1.0
    return out


def lagrangian_cost(base: torch.Tensor, directions: torch.Tensor, mu: torch.Tensor) -> torch.Tensor:
    """``C(μ) = C₀ + Σ_i μ_i A_i``, summed in the order of i; a defer row of ``C₀`` is left as is.

    Args:
        base: C₀, (N, N) or (N + 1, N).
        directions: (K, N, N) from :func:`lagrangian_directions`.
        mu: (K,) or (P, K) multipliers ≥ 0.

    Returns:
        (R, N), or (P, R, N) for (P, K) multipliers (R = N or N + 1), float64.

    Raises:
        ValueError: a negative or non-finite multiplier, or shapes that do not fit.

    >>> from costseg.costs import symmetric_cost
    >>> C = lagrangian_cost(symmetric_cost(2), lagrangian_directions([(1, "recall")], 2), [3.0])
    >>> C.tolist()
    [[0.0, 4.0], [1.0, 0.0]]
    """
    base = torch.as_tensor(base, dtype=torch.float64)
    directions = torch.as_tensor(directions, dtype=torch.float64)
    mu = torch.as_tensor(mu, dtype=torch.float64)
    n, k = base.shape[-1], directions.shape[0]
    if directions.shape != (k, n, n) or mu.shape[-1:] != (k,) or mu.dim() > 2:
        raise ValueError(
            f"shapes do not fit: base {tuple(base.shape)}, directions {tuple(directions.shape)} "
            f"(want ({k}, {n}, {n})), mu {tuple(mu.shape)} (want ({k},) or (P, {k}))"
        )
    if not (torch.isfinite(mu) & (mu >= 0)).all():
        raise ValueError(f"multipliers must be finite and >= 0, got {mu.tolist()}")
    batch = mu.reshape(-1, k)
    cost = base.expand(len(batch), *base.shape).clone()
    for i in range(k):
        cost[:, :n] = cost[:, :n] + batch[:, i, None, None] * directions[i]
    return cost.reshape(*mu.shape[:-1], *base.shape)


def lagrangian_multipliers(
    cost: torch.Tensor, base: torch.Tensor, directions: torch.Tensor, tolerance: float = 1e-6
) -> torch.Tensor:
    """The multipliers μ with ``lagrangian_cost(base, directions, μ) = cost`` (the inverse of
    :func:`lagrangian_cost`): each μ_i read where A_i alone moves the matrix (the median of
    those entries), else by least squares; (K,) float64.

    Raises:
        ValueError: ``cost`` is not ``C₀ + Σ_i μ_i A_i`` with every μ_i ≥ 0 (within
            ``tolerance`` times its largest entry), or shapes that do not fit.

    >>> from costseg.costs import symmetric_cost
    >>> A = lagrangian_directions([(1, "recall"), (0, "precision")], 3)
    >>> C = lagrangian_cost(symmetric_cost(3), A, [2.0, 0.5])
    >>> lagrangian_multipliers(C, symmetric_cost(3), A).tolist()
    [2.0, 0.5]
    """
    cost = torch.as_tensor(cost, dtype=torch.float64)
    base = torch.as_tensor(base, dtype=torch.float64)
    directions = torch.as_tensor(directions, dtype=torch.float64)
    if cost.shape != base.shape or directions.shape[1:] != base.shape:
        raise ValueError(
            f"a matrix {tuple(cost.shape)} is not of the space of C₀ {tuple(base.shape)} and "
            f"directions {tuple(directions.shape)}"
        )
    system = directions.reshape(len(directions), -1).T  # (N², K)
    moved = (cost - base).reshape(-1)
    mu = torch.linalg.lstsq(system, moved[:, None]).solution[:, 0]
    alone = (system != 0) & ((system != 0).sum(1, keepdim=True) == 1)
    for i in range(len(mu)):
        if alone[:, i].any():
            mu[i] = (moved[alone[:, i]] / system[alone[:, i], i]).median()
    scale = tolerance * max(1.0, cost.abs().max().item())
    rebuilt = base + (mu[:, None, None] * directions).sum(0)
    if (rebuilt - cost).abs().max() > scale or (mu < -scale).any():
        raise ValueError("the matrix is not C₀ + Σ μ_i A_i, every μ_i >= 0, for these constraints")
    return mu.clamp(min=0)


def multiplier_grid(
    dimensions: int, size: int = 6, low: float = 1e-2, high: float = 1e2
) -> torch.Tensor:
    """Every combination of multipliers ``0, low … high`` (``size − 1`` log-spaced values)
    over ``dimensions`` constraints: (size^K, K) float64, the first dimension slowest.

    >>> multiplier_grid(1).tolist()                  # 0 and the decades 0.01 … 100
    [[0.0], [0.01], [0.1], [1.0], [10.0], [100.0]]
    >>> multiplier_grid(1, 4).tolist()
    [[0.0], [0.01], [1.0], [100.0]]
    >>> multiplier_grid(2, 2).tolist()
    [[0.0, 0.0], [0.0, 0.01], [0.01, 0.0], [0.01, 0.01]]
    """
    if dimensions < 1 or size < 2 or not 0 < low <= high or not math.isfinite(high):
        raise ValueError(
            f"a multiplier grid needs dimensions >= 1, size >= 2 and 0 < low <= high; got "
            f"{dimensions}, {size}, {low}, {high}"
        )
    steps = size - 1  # log-spaced values after 0, both ends exactly as given
    span = math.log10(high) - math.log10(low)
    inner = [float(10.0 ** (math.log10(low) + span * s / (steps - 1))) for s in range(1, steps - 1)]
    values = [0.0, low, *inner, high] if steps > 1 else [0.0, low]
    return torch.tensor(list(itertools.product(values, repeat=dimensions)), dtype=torch.float64)


def defer_parameter(names: tuple[str, ...], defers: bool) -> tuple[str, ...]:
    """A space's parameter names, with ``defer`` last when a defer row is part of it."""
    return (*names, "defer") if defers else names


def grid_with_defer(points: torch.Tensor, defer_costs: Sequence[float]) -> torch.Tensor:
    """(P, D) grid points × defer costs → (P·V, D + 1), the defer cost fastest; unchanged when
    there are none.

    >>> grid_with_defer(torch.tensor([[0.0], [1.0]]), [0.2, 0.5]).tolist()
    [[0.0, 0.2], [0.0, 0.5], [1.0, 0.2], [1.0, 0.5]]
    """
    if not defer_costs:
        return points
    defer = torch.as_tensor(list(defer_costs), dtype=torch.float64)
    rows = points.repeat_interleave(len(defer), dim=0)
    return torch.cat([rows, defer.repeat(len(points))[:, None]], dim=1)


def split_defer(
    values: Sequence[float] | torch.Tensor, defers: bool
) -> tuple[torch.Tensor, float | None]:
    """A parameter vector → (the space's own parameters, the defer cost or None)."""
    values = torch.as_tensor(values, dtype=torch.float64).reshape(-1)
    return (values[:-1], float(values[-1])) if defers else (values, None)


@dataclass(frozen=True)
class Hull:
    """A set holding the class rows (the first N) of every candidate of a space: the convex hull
    of ``vertices`` plus ``Σ_g t_g · generators[g]`` with every ``t_g ∈ [0, 1]``.

    An expected cost ``Σ_j C[k, j] p_j`` is linear in C, so its smallest value over the set is its
    smallest over the vertices plus, for each generator, its negative part: the bound with which
    the search keeps every pixel some candidate may decide as a class (docs/definitions.md §20).

    Attributes:
        vertices: (V, N, N) float64, V >= 1.
        generators: (G, N, N) float64, G >= 0.
    """

    vertices: torch.Tensor
    generators: torch.Tensor


@dataclass(frozen=True)
class RegionalHull:
    """A :class:`Hull` per RoI id (index 0: the pixels in no RoI) of a regional space: a pixel
    of RoI r is decided by a matrix of ``regions[r]``."""

    regions: tuple[Hull, ...]


@dataclass(frozen=True)
class TriangleSpace:
    """The mixtures ``α·A + β·B + γ·C`` of three vertex matrices on a barycentric grid of
    ``step`` (:func:`costseg.costs.barycentric_grid`), parameters ``(alpha, beta, gamma)`` and,
    with ``defer_costs``, each point at each defer cost.

    >>> from costseg.costs import symmetric_cost
    >>> from costseg.rules.triangle import vertex_matrices
    >>> space = TriangleSpace(vertex_matrices(["robotistic", "altruistic", "egoistic"]), 0.5)
    >>> space.grid().shape, space.matrix([1.0, 0.0, 0.0]).equal(symmetric_cost(19))
    (torch.Size([6, 3]), True)
    """

    vertices: torch.Tensor
    step: float
    defer_costs: tuple[float, ...] = ()
    name: str = field(default="triangle", init=False)

    @property
    def parameters(self) -> tuple[str, ...]:
        return defer_parameter(("alpha", "beta", "gamma"), bool(self.defer_costs))

    def grid(self) -> torch.Tensor:
        """(P, D) every grid point (at every defer cost), in the triangle's order."""
        return grid_with_defer(barycentric_grid(self.step), self.defer_costs)

    def hull(self) -> Hull:
        """Every mixture lies in the triangle of its three vertices."""
        vertices = torch.as_tensor(self.vertices, dtype=torch.float64)
        n = vertices.shape[-1]
        return Hull(vertices[:, :n], vertices.new_zeros(0, n, n))

    def matrix(self, values: Sequence[float] | torch.Tensor) -> torch.Tensor:
        weights, defer = split_defer(values, bool(self.defer_costs))
        if weights.shape != (3,):
            raise ValueError(f"a triangle point has 3 weights, got {weights.tolist()}")
        cost = mix_costs(torch.as_tensor(self.vertices, dtype=torch.float64), weights[None])[0]
        return cost if defer is None else with_defer(cost, defer)


@dataclass(frozen=True)
class LagrangianSpace:
    """``C(μ) = C₀ + Σ_i μ_i A_i`` (:func:`lagrangian_cost`) on :func:`multiplier_grid`'s points,
    parameters ``mu_1 … mu_K`` and, with ``defer_costs``, each point at each defer cost (then
    ``base`` must be square): the defer row is the defer cost plus ``Σ_i μ_i d_i`` with
    ``deferring`` the (K, N) rows d_i of :func:`defer_directions` (None: zeros).

    >>> from costseg.costs import symmetric_cost
    >>> space = LagrangianSpace(symmetric_cost(2), lagrangian_directions([(0, "recall")], 2),
    ...                         size=2, defer_costs=(0.3,))
    >>> space.parameters, space.matrix([1.0, 0.3]).tolist()
    (('mu_1', 'defer'), [[0.0, 1.0], [2.0, 0.0], [0.3, 0.3]])
    """

    base: torch.Tensor
    directions: torch.Tensor
    size: int = 6
    low: float = 1e-2
    high: float = 1e2
    defer_costs: tuple[float, ...] = ()
    deferring: torch.Tensor | None = None
    name: str = field(default="lagrangian", init=False)

    def __post_init__(self) -> None:
        n = self.base.shape[-1]
        if self.defer_costs and self.base.shape != (n, n):
            raise ValueError("C₀ already has a defer row: give defer costs to it or to the space")

    @property
    def parameters(self) -> tuple[str, ...]:
        names = tuple(f"mu_{i + 1}" for i in range(len(self.directions)))
        return defer_parameter(names, bool(self.defer_costs))

    def grid(self) -> torch.Tensor:
        points = multiplier_grid(len(self.directions), self.size, self.low, self.high)
        return grid_with_defer(points, self.defer_costs)

    def hull(self) -> Hull:
        """``C₀ + Σ_i μ_i A_i`` with every μ_i in [0, high]: the grid's points and the continuous
        search's (:func:`costseg.calibration.design_search.search_multipliers`) alike."""
        base = torch.as_tensor(self.base, dtype=torch.float64)
        n = base.shape[-1]
        directions = torch.as_tensor(self.directions, dtype=torch.float64)
        return Hull(base[None, :n], self.high * directions)

    def matrix(self, values: Sequence[float] | torch.Tensor) -> torch.Tensor:
        mu, defer = split_defer(values, bool(self.defer_costs))
        cost = lagrangian_cost(self.base, self.directions, mu)
        if defer is None:
            return cost
        row = torch.full((cost.shape[-1],), defer, dtype=torch.float64)
        if self.deferring is not None:
            row = row + (mu[:, None] * torch.as_tensor(self.deferring, dtype=torch.float64)).sum(0)
        return with_defer(cost, row)


def constraints_moving(regions: Sequence[int], region: int) -> torch.Tensor:
    """(K,) float64 1 for each constraint whose RoI ``regions[i]`` moves the matrix of RoI
    ``region`` (its own RoI, or RoI 0, the whole image, which moves every matrix), else 0.

    >>> constraints_moving([1, 0, 3], 1).tolist(), constraints_moving([1, 0, 3], 0).tolist()
    ([1.0, 1.0, 0.0], [0.0, 1.0, 0.0])
    """
    return torch.tensor([float(r in (region, 0)) for r in regions], dtype=torch.float64)


@dataclass(frozen=True)
class RegionalLagrangianSpace(LagrangianSpace):
    """The Lagrangian space by region (docs/definitions.md §21): constraint i, on RoI
    ``regions[i]``, moves only that RoI's matrix (RoI 0, the whole image, moves every one):
    ``C_r(μ) = C₀_r + Σ_{i : r_i = r or r_i = 0} μ_i A_i`` for r = 0 … R (0: the pixels in no
    RoI), the rest of the image keeping C₀. ``base`` is one matrix (every region's C₀) or a
    regional stack (R + 1, N(+1), N); a candidate is the stack (R + 1, N(+1), N). Parameters,
    grid, defer costs as :class:`LagrangianSpace`; each region's matrix is that space's with the
    directions of the constraints that move it (:meth:`region`).

    >>> from costseg.costs import symmetric_cost
    >>> space = RegionalLagrangianSpace(symmetric_cost(2), lagrangian_directions([(1, "recall")],
    ...                                 2), size=2, regions=(1,))
    >>> stack = space.matrix([3.0])
    >>> stack.shape, stack[1, 0, 1].item(), stack[2, 0, 1].item()   # RoI 1 moves, RoI 2 stays
    (torch.Size([5, 2, 2]), 4.0, 1.0)
    """

    regions: tuple[int, ...] = ()
    name: str = "regional"

    def __post_init__(self) -> None:
        if len(self.regions) != len(self.directions):
            raise ValueError(f"{len(self.directions)} constraints need as many RoIs, got "
                             f"{list(self.regions)}")  # fmt: skip
        if not all(0 <= r <= NUM_ROIS for r in self.regions):
            raise ValueError(f"RoIs of the constraints lie in 0 … {NUM_ROIS}, got "
                             f"{list(self.regions)}")  # fmt: skip
        self.region(0)  # the checks of a plain space

    def bases(self) -> torch.Tensor:
        """(R + 1, N(+1), N) every region's C₀."""
        base = torch.as_tensor(self.base, dtype=torch.float64)
        return base if is_regional(base) else base.expand(NUM_ROIS + 1, *base.shape)

    def region(self, r: int) -> LagrangianSpace:
        """The plain Lagrangian space of RoI r's matrix: its C₀ and the directions (and defer
        directions) of the constraints that move it, zero for the others."""
        moves = constraints_moving(self.regions, r)
        deferring = None if self.deferring is None else self.deferring * moves[:, None]
        return LagrangianSpace(self.bases()[r], self.directions * moves[:, None, None], self.size,
                               self.low, self.high, self.defer_costs, deferring)  # fmt: skip

    def hull(self) -> RegionalHull:
        """Each region's :meth:`LagrangianSpace.hull`: a pixel of RoI r is changed only by the
        constraints that move r."""
        return RegionalHull(tuple(self.region(r).hull() for r in range(NUM_ROIS + 1)))

    def matrix(self, values: Sequence[float] | torch.Tensor) -> torch.Tensor:
        """(R + 1, N(+1), N): each region's matrix at ``values``."""
        return torch.stack([self.region(r).matrix(values) for r in range(NUM_ROIS + 1)])


@dataclass(frozen=True)
class AggregateTemplate:
    """An aggregate cost file (§2): everything but its matrix (the aggregate table, their order,
    ε, M, s), read once; :meth:`matrix` fills in a matrix."""

    spec: dict
    folder: Path
    class_names: tuple[str, ...] = CLASS_NAMES

    @property
    def order(self) -> tuple[str, ...]:
        return tuple(self.spec["order"])

    def entries(self) -> torch.Tensor:
        """The file's own A(A − 1) off-diagonal aggregate costs, row by row."""
        matrix = torch.tensor(self.spec["matrix"], dtype=torch.float64)
        return off_diagonal(matrix)

    def matrix(self, aggregate: torch.Tensor) -> torch.Tensor:
        """(A, A) aggregate costs → the validated (N, N) class matrix (by
        :func:`costseg.costs.expand_aggregates`)."""
        spec = {**self.spec, "matrix": torch.as_tensor(aggregate, dtype=torch.float64).tolist()}
        cost = expand_aggregates(spec, self.folder, self.class_names)
        return validate_cost(cost, self.class_names)


def aggregate_template(
    name_or_path: str | Path = "altruistic", class_names: Sequence[str] = CLASS_NAMES
) -> AggregateTemplate:
    """The aggregate cost file ``name_or_path`` (a preset name or a YAML path) as a template.

    Raises:
        ValueError: the file has no aggregates (a full or symmetric matrix), or has a defer row.

    >>> aggregate_template().order
    ('road', 'flat', 'static', 'info', 'human', 'dynamic')
    """
    if str(name_or_path) in PRESETS:
        path = COSTS_DIR / f"{name_or_path}.yaml"
    else:
        path = Path(name_or_path)
    spec = read_yaml(path)
    if not {"aggregates", "order", "matrix"} <= spec.keys():
        raise ValueError(f"{path}: an aggregate design space needs an aggregate cost file (§2)")
    if "defer" in spec:
        raise ValueError(f"{path}: give the defer cost to the design space, not the template")
    return AggregateTemplate(spec, Path(str(path)).parent, tuple(class_names))


def aggregate_matrix(entries: torch.Tensor, size: int) -> torch.Tensor:
    """A(A − 1) off-diagonal entries, row by row → the (A, A) matrix with a zero diagonal
    (the inverse of :func:`costseg.costs.off_diagonal`).

    >>> aggregate_matrix(torch.tensor([1.0, 2, 3, 4, 5, 6]), 3).tolist()
    [[0.0, 1.0, 2.0], [3.0, 0.0, 4.0], [5.0, 6.0, 0.0]]
    """
    entries = torch.as_tensor(entries, dtype=torch.float64).reshape(-1)
    if entries.shape != (size * (size - 1),):
        raise ValueError(f"{size} aggregates have {size * (size - 1)} off-diagonal costs, got "
                         f"{len(entries)}")  # fmt: skip
    matrix = torch.zeros(size, size, dtype=torch.float64)
    matrix[~torch.eye(size, dtype=torch.bool)] = entries
    return matrix


@dataclass(frozen=True)
class AggregateSpace:
    """The aggregate matrix of ``template`` with its A(A − 1) off-diagonal costs free in
    ``[low, high]`` (searched on a log scale), expanded to the class matrix by §2's rules;
    with ``defer_box`` a scalar defer cost in that box, the last parameter.

    Parameters are named ``predicted>true`` by aggregate, row by row.

    >>> from costseg.costs import load_cost
    >>> space = AggregateSpace(aggregate_template("altruistic"))
    >>> len(space.parameters), space.parameters[0], space.box()[0]
    (30, 'road>flat', ('road>flat', 0.1, 1000.0))
    >>> torch.equal(space.matrix(space.template.entries()), load_cost("altruistic"))
    True
    """

    template: AggregateTemplate
    low: float = 0.1
    high: float = 1000.0
    defer_box: tuple[float, float] | None = None
    name: str = field(default="aggregate", init=False)

    def __post_init__(self) -> None:
        boxes = [(self.low, self.high), *([self.defer_box] if self.defer_box else [])]
        if not all(0 < lo <= hi and math.isfinite(hi) for lo, hi in boxes):
            raise ValueError(f"a log-scale box needs 0 < low <= high < inf; got {boxes}")

    @property
    def parameters(self) -> tuple[str, ...]:
        order = self.template.order
        names = tuple(f"{a}>{b}" for a in order for b in order if a != b)
        return defer_parameter(names, self.defer_box is not None)

    def hull(self) -> None:
        """None: §2's expansion of the aggregates gives no bound here, so the search keeps every
        pixel of a constraint's RoI."""
        return None

    def box(self) -> list[tuple[str, float, float]]:
        """(name, low, high) of each parameter, all on a log scale."""
        boxes = [(self.low, self.high)] * (len(self.parameters) - (self.defer_box is not None))
        boxes += [self.defer_box] if self.defer_box else []
        return [(n, lo, hi) for n, (lo, hi) in zip(self.parameters, boxes, strict=True)]

    def matrix(self, values: Sequence[float] | torch.Tensor) -> torch.Tensor:
        entries, defer = split_defer(values, self.defer_box is not None)
        cost = self.template.matrix(aggregate_matrix(entries, len(self.template.order)))
        return cost if defer is None else with_defer(cost, defer, self.template.class_names)
