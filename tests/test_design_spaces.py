"""Design spaces against docs/definitions.md §20: the Lagrangian matrix against the formula on a
hand-made case and against npcs' rule, the aggregate space against the paper's matrices, the
grids against their definitions."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
import torch
from test_costs import C_A, C_E

from costseg.costs import barycentric_grid, load_cost, symmetric_cost
from costseg.decision import decide_reference
from costseg.metrics.names import TARGET_METRICS
from costseg.rules.design_spaces import (
    PRECISION_TYPE,
    RECALL_TYPE,
    AggregateSpace,
    LagrangianSpace,
    TriangleSpace,
    aggregate_template,
    constraint_kind,
    defer_directions,
    lagrangian_cost,
    lagrangian_directions,
    multiplier_grid,
)
from costseg.rules.triangle import vertex_matrices

# The paper's 6×6 matrices (definitions §2), retyped in test_costs: the tests read no file.
ALTRUISTIC, EGOISTIC = C_A, C_E


def entries(matrix: list[list[float]]) -> list[float]:
    return [matrix[i][j] for i in range(6) for j in range(6) if i != j]


def test_constraint_kinds_name_target_metrics_and_refuse_the_rest() -> None:
    assert set(RECALL_TYPE) | set(PRECISION_TYPE) <= set(TARGET_METRICS)
    for metric in TARGET_METRICS:
        if metric in RECALL_TYPE or metric in PRECISION_TYPE:
            assert constraint_kind(metric) == ("recall" if metric in RECALL_TYPE else "precision")
        else:
            with pytest.raises(ValueError, match=f"cannot steer '{metric}'") as err:
                constraint_kind(metric)
            assert "\n" not in str(err.value)
    assert constraint_kind("instance_recall") == "recall"
    assert constraint_kind("fp_rate") == "precision"


def test_lagrangian_matrix_equals_the_formula_on_a_hand_made_case() -> None:
    base = torch.tensor([[0, 2, 3], [4, 0, 5], [6, 7, 0], [0.3, 0.2, 0.1]], dtype=torch.float64)
    directions = lagrangian_directions([(0, "recall"), (2, "precision")], 3)
    # recall of class 0: +2 on column 0 below and above the diagonal; precision of class 2:
    # +0.5 on row 2 off the diagonal; the defer row stays
    want = [[0, 2, 3], [6, 0, 5], [8.5, 7.5, 0], [0.3, 0.2, 0.1]]
    assert lagrangian_cost(base, directions, [2.0, 0.5]).tolist() == want
    batch = lagrangian_cost(base, directions, torch.tensor([[0.0, 0.0], [2.0, 0.5]]))
    assert batch.shape == (2, 4, 3) and batch[0].equal(base) and batch[1].tolist() == want
    with pytest.raises(ValueError, match="multipliers"):
        lagrangian_cost(base, directions, [-1.0, 0.0])
    with pytest.raises(ValueError, match="outside"):
        lagrangian_directions([(3, "recall")], 3)


def test_recall_multipliers_on_the_symmetric_matrix_are_npcs_rule() -> None:
    """C₀ = 1 − I with recall constraints: argmin Σ C p = argmax (1 + μ_k) p_k."""
    rng = np.random.default_rng(3)
    n = 6
    classes = [1, 4, 5]
    directions = lagrangian_directions([(c, "recall") for c in classes], n)
    for mu in [rng.exponential(1.0, 3), np.array([0.0, 0.1, 10.0]), np.array([100.0, 0, 1])]:
        probs = rng.dirichlet(np.full(n, 0.7), size=(40, 50)).transpose(2, 0, 1)[None]
        cost = lagrangian_cost(symmetric_cost(n), directions, torch.tensor(mu))
        weights = np.ones(n)
        weights[classes] += mu
        want = np.argmax(weights[:, None, None] * probs[0], axis=0)
        got = decide_reference(torch.tensor(probs), cost)[0].numpy()
        assert (got == want).all()


def test_multiplier_grid_is_every_combination_first_dimension_slowest() -> None:
    values = [0.0, 0.01, 0.1, 1.0, 10.0, 100.0]
    grid = multiplier_grid(2)
    assert grid.tolist() == [list(v) for v in itertools.product(values, repeat=2)]
    assert multiplier_grid(3, 3, 0.5, 2.0).tolist()[:4] == [
        [0, 0, 0], [0, 0, 0.5], [0, 0, 2], [0, 0.5, 0]
    ]  # fmt: skip
    with pytest.raises(ValueError, match="multiplier grid"):
        multiplier_grid(1, 1)


def test_lagrangian_space_with_a_defer_parameter() -> None:
    directions = lagrangian_directions([(0, "recall"), (1, "fp_rate")], 3)
    space = LagrangianSpace(symmetric_cost(3), directions, size=2, defer_costs=(0.2, 0.4))
    assert space.parameters == ("mu_1", "mu_2", "defer")
    grid = space.grid()
    assert grid.shape == (8, 3) and grid[:2, 2].tolist() == [0.2, 0.4]
    matrix = space.matrix(grid[-1])
    want = lagrangian_cost(symmetric_cost(3), directions, grid[-1, :2])
    assert matrix[:3].equal(want) and matrix[3].tolist() == [0.4] * 3
    with pytest.raises(ValueError, match="defer row"):
        LagrangianSpace(torch.cat([symmetric_cost(3), torch.ones(1, 3)]), directions,
                        defer_costs=(0.1,))  # fmt: skip
    # a recall that counts a deferral as a miss makes deferring its class cost more too
    pairs = [(0, "recall"), (1, "handled_recall"), (2, "precision")]
    directions, rows = lagrangian_directions(pairs, 3), defer_directions(pairs, 3)
    deferring = LagrangianSpace(symmetric_cost(3), directions, defer_costs=(0.2,), deferring=rows)
    assert deferring.matrix([5.0, 7.0, 11.0, 0.2])[3].tolist() == [5.2, 0.2, 0.2]


def test_aggregate_space_with_the_papers_matrices_reproduces_the_presets() -> None:
    space = AggregateSpace(aggregate_template("altruistic"))
    assert len(space.parameters) == 30 and space.parameters[:2] == ("road>flat", "road>static")
    assert torch.equal(space.matrix(entries(ALTRUISTIC)), load_cost("altruistic"))
    # ε, M, s are the same in both files: the altruistic template takes egoistic costs too
    assert torch.equal(space.matrix(entries(EGOISTIC)), load_cost("egoistic"))
    assert space.template.entries().tolist() == entries(ALTRUISTIC)
    with_defer = AggregateSpace(aggregate_template("altruistic"), defer_box=(0.01, 10.0))
    matrix = with_defer.matrix([*entries(ALTRUISTIC), 0.5])
    assert matrix.shape == (20, 19) and matrix[:19].equal(load_cost("altruistic"))
    assert matrix[19].eq(0.5).all() and with_defer.box()[-1] == ("defer", 0.01, 10.0)
    with pytest.raises(ValueError, match="off-diagonal"):
        space.matrix(entries(ALTRUISTIC)[:29])
    with pytest.raises(ValueError, match="aggregate cost file"):
        aggregate_template("robotistic")
    with pytest.raises(ValueError, match="box"):
        AggregateSpace(aggregate_template("altruistic"), 0.0, 10.0)


def test_triangle_space_is_the_mixture_of_its_vertices() -> None:
    vertices = vertex_matrices(["robotistic", "altruistic", "egoistic"])
    space = TriangleSpace(vertices, 0.25, defer_costs=(0.5,))
    grid = space.grid()
    assert grid[:, :3].equal(barycentric_grid(0.25)) and space.parameters[-1] == "defer"
    for point in grid:
        a, b, c = point[:3].tolist()
        want = (a * vertices[0] + b * vertices[1]) + c * vertices[2]
        got = space.matrix(point)
        assert got[:19].equal(want) and got[19].eq(0.5).all()
