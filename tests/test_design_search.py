"""The design search: grid spaces scored point by point, the aggregate space by Optuna (the same
candidates for a seed, feasible points found where the feasible region is known)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from costseg.calibration.design_search import search, search_aggregate, search_grid
from costseg.costs import symmetric_cost
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


def test_pooled_counts_and_image_losses_equal_a_loop_over_the_images() -> None:
    """The design's scorer pools a matrix's counts batch by batch (``Pooled``) and takes each
    image's constraint losses from them (``image_losses``): equal to deciding each image alone
    with ``decide_reference`` and counting by hand."""
    from costseg.decision import decide_reference, prepare_counts
    from costseg.decision.counts import count_decisions
    from costseg.evaluation.analyses.design import Pooled, d1_images, image_losses
    from costseg.metrics.requirements import Requirements

    g = torch.Generator().manual_seed(0)
    probs = (3 * torch.randn(5, 19, 8, 16, generator=g)).softmax(1)
    labels = probs.argmax(1)
    labels[torch.rand(labels.shape, generator=g) < 0.3] = 11  # persons, some of them missed
    labels[:, 0] = 255
    roi = torch.randint(0, 5, labels.shape, generator=g)
    req = Requirements.parse(["person:roi1:recall>=0.5", "car:roi0:precision>=0.5"])
    cost = symmetric_cost(19)
    cost[:, 11] *= 3  # a person missed costs more
    pooled, losses = Pooled(), []
    for batch in (slice(0, 2), slice(2, 5)):
        first = batch.start
        assert d1_images(first, batch.stop - first, 2) == (2 if first == 0 else 0)
        inputs = prepare_counts(probs[batch], labels[batch], roi[batch])
        counts = count_decisions(inputs, cost)
        pooled.add(counts)
        losses.append(image_losses(req, counts, cost))
    decided = decide_reference(probs, cost)
    labelled = labels != 255
    assert pooled.agree == (labelled & (decided == probs.argmax(1))).sum()
    want = []
    for i in range(5):
        person, street = labels[i] == 11, roi[i] == 1
        recall = (person & street & (decided[i] == 11)).sum() / (person & street).sum()
        car = (decided[i] == 13) & labelled[i]
        precision = (car & (labels[i] == 13)).sum() / car.sum()
        want.append([1 - recall.item(), 1 - precision.item()])
    torch.testing.assert_close(torch.cat(losses).double(), torch.tensor(want).double(),
                               equal_nan=True)  # fmt: skip
