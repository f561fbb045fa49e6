"""The design search: grid spaces scored point by point, the aggregate space by Optuna (the same
candidates for a seed, feasible points found where the feasible region is known)."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
import torch

from costseg.calibration.design_search import (
    search,
    search_aggregate,
    search_grid,
    search_multipliers,
)
from costseg.calibration.guarantee import hoeffding_bentkus_pvalue
from costseg.costs import load_cost, symmetric_cost
from costseg.decision import decide_reference
from costseg.rules.design_spaces import (
    AggregateSpace,
    LagrangianSpace,
    aggregate_template,
    lagrangian_directions,
)

HUMAN, ROAD = 11, 0  # person, road


def toy_score(cost: torch.Tensor) -> tuple[list[float], float]:
    """Risks with a known feasible region: missing a person on the road must cost ≥ 190
    (risk 1 ≤ 0.05) and calling the road a person ≤ 10 (risk 2 ≤ 0.5); the objective prefers
    small costs overall."""
    miss, false_alarm = cost[ROAD, HUMAN].item(), cost[HUMAN, ROAD].item()
    return [10 / (10 + miss), false_alarm / (false_alarm + 10)], -float(cost.log1p().mean())


def toy_risks(matrices: torch.Tensor) -> np.ndarray:
    """(L, 2) the toy risks of each candidate, from its matrix."""
    return np.array([toy_score(matrix)[0] for matrix in matrices])


def feasible(risks: np.ndarray, alphas=(0.05, 0.5)) -> np.ndarray:
    return (risks <= np.array(alphas)).all(axis=1)


def test_grid_search_scores_every_point_in_order() -> None:
    directions = lagrangian_directions([(1, "recall"), (2, "precision")], 3)
    space = LagrangianSpace(symmetric_cost(3), directions, size=3)
    seen = []

    def score(cost):
        seen.append(cost)
        return [cost[0, 1].item() / 100, cost[2, 0].item() / 200], float(len(seen))

    found = search_grid(space, score)
    grid = space.grid()
    assert found.names == ("mu_1", "mu_2") and found.space == "lagrangian"
    assert np.array_equal(found.parameters, grid.numpy()) and len(seen) == len(grid) == 9
    for point, matrix, scored in zip(grid, found.matrices, seen, strict=True):
        assert matrix.equal(space.matrix(point)) and scored.equal(matrix)
    assert found.objective.tolist() == list(range(1, 10))


def test_aggregate_search_is_reproducible_for_a_seed() -> None:
    space = AggregateSpace(aggregate_template("altruistic"), 0.1, 1000.0, defer_box=(0.01, 1.0))
    runs = [search_aggregate(space, toy_score, [0.05, 0.5], 30, seed=s, population=10)
            for s in (7, 7, 8)]  # fmt: skip
    assert runs[0].parameters.shape == (30, 31) and runs[0].names[-1] == "defer"
    assert np.array_equal(runs[0].parameters, runs[1].parameters)
    assert torch.equal(runs[0].matrices, runs[1].matrices)
    assert np.array_equal(runs[0].objective, runs[1].objective)
    assert not np.array_equal(runs[0].parameters[1:], runs[2].parameters[1:])
    # the first candidate is the template itself (the defer cost at the box's log middle)
    assert runs[0].parameters[0, :30].tolist() == space.template.entries().tolist()
    assert runs[0].matrices.shape == (30, 20, 19)


def test_the_continuous_search_is_seeded_starts_at_the_anchors_and_finds_the_boundary() -> None:
    """The Lagrangian multipliers searched by Optuna over log μ: μ = 0 and the box's corners
    first (the most cautious corner second), every μ in {0} ∪ [low, high], the same candidates
    for a seed and others for another; steered by the constraints (D1's p-values <= δ), it
    samples them far more often than a uniform draw over log μ (about 7 % here)."""
    directions = lagrangian_directions([(HUMAN, "recall"), (ROAD, "precision")], 19)
    space = LagrangianSpace(symmetric_cost(19), directions, defer_costs=(0.2, 0.5))

    def score(cost):  # risk 1 falls with μ_1, risk 2 with μ_2; the objective prefers small μ
        mu_1, mu_2 = cost[1, HUMAN].item() - 1, cost[ROAD, 1].item() - 1
        risks = [1 / (1 + mu_1), 1 / (1 + mu_2)]
        return risks, -np.log1p(mu_1) - np.log1p(mu_2), [400, 400]

    runs = [search_multipliers(space, score, [0.1, 0.2], 60, seed=s, delta=0.1) for s in (1, 1, 2)]
    found = runs[0]
    assert found.names == ("mu_1", "mu_2", "defer") and found.parameters.shape == (60, 3)
    assert found.parameters[:4].tolist() == [[0, 0, 0.2], [0, 0, 0.5], [100, 100, 0.2],
                                              [100, 100, 0.5]]  # fmt: skip
    mu = found.parameters[:, :2]
    assert (((mu >= 0.01) & (mu <= 100)) | (mu == 0)).all()
    assert set(found.parameters[:, 2].tolist()) == {0.2, 0.5}
    assert np.array_equal(runs[0].parameters, runs[1].parameters)
    assert not np.array_equal(runs[0].parameters[10:], runs[2].parameters[10:])
    for matrix, values in zip(found.matrices, found.parameters, strict=True):
        assert torch.equal(matrix, space.matrix(values))
    risks = np.array([score(matrix)[0] for matrix in found.matrices])
    pvalues = [hoeffding_bentkus_pvalue(risks[:, i], 400, a) for i, a in enumerate([0.1, 0.2])]
    feasible = np.max(pvalues, axis=0) <= 0.1
    assert feasible[30:].mean() > 0.25


def test_aggregate_search_finds_the_feasible_region() -> None:
    space = AggregateSpace(aggregate_template("altruistic"), 0.1, 1000.0)
    found = search(space, toy_score, [0.05, 0.5], budget=120, seed=0)
    ok = feasible(toy_risks(found.matrices))
    # about 9 % of the box is feasible: a search steered by the constraints finds more of it
    # in its later generations than in its first (random) one
    assert ok.any() and ok[60:].mean() > ok[:40].mean()
    for matrix, objective in zip(found.matrices[ok], found.objective[ok], strict=True):
        assert matrix[ROAD, HUMAN] >= 190 and matrix[HUMAN, ROAD] <= 10
        assert objective == toy_score(matrix)[1]


def test_aggregate_search_refuses_bad_settings() -> None:
    space = AggregateSpace(aggregate_template("altruistic"))
    with pytest.raises(ValueError, match="budget"):
        search_aggregate(space, toy_score, [0.1, 0.1], 0)
    with pytest.raises(ValueError, match="2 risks for 1 alphas"):
        search_aggregate(space, toy_score, [0.1], 2)


def _scene(seed: int = 0, b: int = 4, h: int = 12, w: int = 20):
    """Probabilities, labels (some unlabelled) and RoIs of ``b`` small images; persons, cars and
    buildings common, their probabilities often not the largest."""
    g = torch.Generator().manual_seed(seed)
    probs = (2.5 * torch.randn(b, 19, h, w, generator=g)).softmax(1)
    labels = probs.argmax(1)
    for cls, share in ((11, 0.25), (13, 0.15), (2, 0.2)):
        labels[torch.rand(labels.shape, generator=g) < share] = cls
    labels[:, 0] = 255
    roi = torch.randint(0, 5, labels.shape, generator=g)
    return probs, labels, roi


REQUIRE = ["person:roi1:recall>=0.5", "person:roi0:precision>=0.5", "building:roi3:precision>=0.5",
           "car:roi2:dice>=0.5"]  # fmt: skip


def _loop_losses(probs, labels, roi, cost, req) -> torch.Tensor:
    """Every image decided alone by ``decide_reference`` on every pixel, each constraint's loss
    counted by hand."""
    out = []
    for i in range(len(probs)):
        decided = decide_reference(probs[i : i + 1], cost)[0]
        row = []
        for t in req.constraints:
            region = (labels[i] != 255) & ((roi[i] == t.roi) if t.roi else True)
            truth, said = region & (labels[i] == t.cls), region & (decided == t.cls)
            tp = (truth & said).sum().item()
            whole = {"recall": truth.sum(), "precision": said.sum(),
                     "dice": (truth.sum() + said.sum()) / 2}[t.metric].item()  # fmt: skip
            row.append(1 - tp / whole if whole else float("nan"))
        out.append(row)
    return torch.tensor(out, dtype=torch.float64)


def test_the_search_risks_equal_an_every_pixel_loop() -> None:
    """The search scores each candidate on the pixels that can change a constraint (and a
    tenth for the objective): its per-image constraint losses, hence its D1 risks, equal
    ``decide_reference`` on every pixel of each image, for candidates across the space (its
    corners, the grid, the continuous search's points) and for the triangle beside it."""
    from costseg.calibration.guarantee import defined_risks
    from costseg.evaluation.analyses.design import SearchImages
    from costseg.metrics.requirements import Requirements
    from costseg.rules.design_spaces import TriangleSpace
    from costseg.rules.triangle import vertex_matrices

    probs, labels, roi = _scene()
    req = Requirements.parse(REQUIRE)
    pairs = [(t.cls, t.metric.replace("dice", "recall")) for t in req.constraints]  # car: column
    lagrangian = LagrangianSpace(load_cost("egoistic"), lagrangian_directions(pairs, 19), size=3)
    triangle = TriangleSpace(vertex_matrices(["robotistic", "altruistic", "egoistic"]), 0.5)
    found = SearchImages()
    hulls = [lagrangian.hull(), triangle.hull()]
    for part in (slice(0, 1), slice(1, 4)):  # two batches, each image its own seed
        seeds = list(range(part.start, part.stop))
        found.add_pixels(probs[part], labels[part], roi[part], 0.1, req, hulls, seeds)
    kept = sum(int((p.inputs.cell >= 0).sum()) for p in found.parts)
    assert kept < 0.8 * int((labels != 255).sum())  # not every pixel: the bound leaves some out
    g = torch.Generator().manual_seed(1)
    points = [*lagrangian.grid()[[0, 5, -1]], *(100 * torch.rand(3, 4, generator=g).pow(3))]
    matrices = [lagrangian.matrix(p) for p in points]
    matrices += [triangle.matrix(p) for p in triangle.grid()]
    for cost in matrices:
        seen = []
        risks, _, defined = found.scorer(req, seen.append)(cost)
        want = _loop_losses(probs, labels, roi, cost, req)
        torch.testing.assert_close(torch.from_numpy(seen[0]), want, equal_nan=True)
        np.testing.assert_allclose(risks, defined_risks(want.numpy())[0])
        assert defined.tolist() == (~want.isnan()).sum(0).tolist()


def test_a_pixel_any_candidate_decides_as_a_class_is_kept() -> None:
    """The hull's bound (search_pixels.could_decide) never leaves out a pixel that some
    candidate decides as the class: checked against decide_reference at the corners and at
    random points of the Lagrangian box and of the triangle."""
    from costseg.calibration.search_pixels import could_decide
    from costseg.rules.design_spaces import TriangleSpace
    from costseg.rules.triangle import vertex_matrices

    probs, _, _ = _scene(seed=2, b=2, h=30, w=40)
    probs[:, :, 0] = 0.01  # a row of exact ties at the base matrix, each broken to class 2
    probs[:, 2, 0] = probs[:, 5, 0] = probs[:, 11, 0] = probs[:, 13, 0] = 0.2125
    pairs = [(11, "recall"), (11, "precision"), (2, "precision")]
    space = LagrangianSpace(load_cost("robotistic"), lagrangian_directions(pairs, 19))
    triangle = TriangleSpace(vertex_matrices(["robotistic", "altruistic", "egoistic"]), 0.1)
    g = torch.Generator().manual_seed(3)
    corners = torch.tensor(list(itertools.product([0.0, 100.0], repeat=3)))
    points = [space.matrix(p) for p in [*corners, *(100 * torch.rand(20, 3, generator=g))]]
    weights = torch.rand(20, 3, generator=g)
    mixtures = [triangle.matrix(w / w.sum()) for w in weights]
    flat = probs.permute(1, 0, 2, 3).reshape(19, -1)  # (N, pixels) in the order of decided
    for hull, costs in ((space.hull(), points), (triangle.hull(), mixtures)):
        possible = {cls: could_decide(flat, cls, hull) for cls in (11, 2, 13)}
        assert not any(p.all() for p in possible.values())  # the bound does leave pixels out
        for cost in costs:
            decided = decide_reference(probs, cost).reshape(-1)
            for cls, p in possible.items():
                assert p[decided == cls].all()
