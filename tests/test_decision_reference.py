"""decide_reference against independent references: a brute-force loop over pixels in plain
Python floats (the same operations in the same order), exact rational arithmetic where float64
sums are exact, and the rule's properties (docs/definitions.md §1)."""

import itertools
from fractions import Fraction

import pytest
import torch
from decision_inputs import VERTICES, near_ties, probabilities
from hypothesis import given, settings
from hypothesis import strategies as st

from costseg.costs import barycentric_grid, mix_costs
from costseg.decision import decide_mixtures_reference, decide_reference, expected_costs


def python_reference(p, cost, priors=None):
    """The rule for one pixel in plain Python floats: q = p / π, the column-shifted matrix, the
    sums over k in ascending order, the first minimum."""
    n = len(p)
    q = [p[k] / (1.0 if priors is None else priors[k]) for k in range(n)]
    shifted = [[cost[j][k] - max(cost[i][k] for i in range(n)) for k in range(n)] for j in range(n)]
    costs = []
    for j in range(n):
        total = 0.0
        for k in range(n):
            total = total + shifted[j][k] * q[k]
        costs.append(total)
    return min(range(n), key=lambda j: (costs[j], j))


def brute_force(probs, cost, priors=None):
    """(B, H, W) labels, pixel by pixel with :func:`python_reference`."""
    b, _, h, w = probs.shape
    cost = cost.double().tolist()
    out = torch.empty(b, h, w, dtype=torch.long)
    for i in range(b):
        for y in range(h):
            for x in range(w):
                pri = None if priors is None else priors if priors.ndim == 1 else priors[:, y, x]
                pri = None if pri is None else pri.double().tolist()
                out[i, y, x] = python_reference(probs[i, :, y, x].double().tolist(), cost, pri)
    return out


@pytest.mark.parametrize("dtype", [torch.float32, torch.float16, torch.bfloat16, torch.float64])
def test_reference_equals_a_loop_over_pixels(dtype):
    gen = torch.Generator().manual_seed(0)
    probs = torch.rand(2, 5, 3, 4, generator=gen).softmax(1).to(dtype)
    probs[0, :, 0, 0] = 0.2  # an exact tie of all classes
    cost = (torch.rand(5, 5, generator=gen, dtype=torch.float64) * 3 + 0.1).fill_diagonal_(0)
    global_priors = torch.rand(5, generator=gen) + 0.05
    pixel_priors = torch.rand(5, 3, 4, generator=gen, dtype=torch.float64) + 0.05
    for priors in (None, global_priors, pixel_priors):
        assert torch.equal(decide_reference(probs, cost, priors), brute_force(probs, cost, priors))
    symmetric = torch.ones(5, 5).fill_diagonal_(0)
    assert torch.equal(decide_reference(probs, None), brute_force(probs, symmetric))


def test_reference_equals_a_loop_at_near_ties():
    cost = VERTICES[2].double()
    probs = near_ties(cost, 210, seed=5)
    expected = brute_force(probs, cost)
    assert torch.equal(decide_reference(probs, cost), expected)
    assert (expected.view(-1, 7) != expected.view(-1, 7)[:, :1]).any()  # decisions flip


@settings(max_examples=100, deadline=None)
@given(probabilities(max_classes=4), st.integers(0, 2**31))
def test_reference_is_exact_arithmetic_on_exact_inputs(probs, seed):
    """Integer costs and probabilities of few levels: float64 sums are exact, ties included."""
    probs = probs.float()
    n = probs.shape[1]
    gen = torch.Generator().manual_seed(seed)
    cost = torch.randint(1, 5, (n, n), generator=gen).double() * (1 - torch.eye(n))
    pixels = probs.permute(0, 2, 3, 1).reshape(-1, n)
    decided = decide_reference(probs, cost).flatten()
    for p, label in zip(pixels.tolist(), decided.tolist(), strict=True):
        exact = [
            sum(Fraction(cost[j, k].item()) * Fraction(p[k]) for k in range(n)) for j in range(n)
        ]
        assert label == min(range(n), key=lambda j: (exact[j], j))
        assert label == python_reference(p, cost.tolist())


def test_symmetric_and_ml_rules():
    gen = torch.Generator().manual_seed(1)
    probs = torch.rand(2, 19, 6, 7, generator=gen).softmax(1).half()  # float16: ties
    assert torch.equal(decide_reference(probs), probs.argmax(1))
    priors = torch.rand(19, 6, 7, generator=gen, dtype=torch.float64) + 0.01
    assert torch.equal(decide_reference(probs, None, priors), (probs.double() / priors).argmax(1))


def test_mixture_reference_is_the_reference_of_each_mixed_matrix():
    probs = torch.rand(1, 19, 3, 4, generator=torch.Generator().manual_seed(2)).softmax(1)
    weights = barycentric_grid(0.5)
    labels = decide_mixtures_reference(probs, VERTICES, weights)
    assert labels.shape == (1, len(weights), 3, 4) and labels.dtype == torch.long
    for k, cost in enumerate(mix_costs(VERTICES, weights)):
        assert torch.equal(labels[:, k], brute_force(probs, cost))


@pytest.mark.parametrize("width", [3, 4])  # 3 = N: a wrong broadcast keeps the shape
def test_expected_costs_with_global_priors_by_hand(width):
    """(N,) priors divide each class's probability at every pixel: Σ_k C[j, k] p_k / π_k summed
    by hand, and the argmin of the expected costs is decide_reference's decision."""
    gen = torch.Generator().manual_seed(3)
    probs = torch.rand(2, 3, 2, width, generator=gen, dtype=torch.float64).softmax(1)
    cost = torch.tensor([[0.0, 4, 1], [2, 0, 8], [1, 3, 0]], dtype=torch.float64)
    priors = torch.tensor([0.5, 0.2, 0.3], dtype=torch.float64)
    got = expected_costs(probs, cost, priors)
    assert got.shape == (2, 3, 2, width)
    for b, y, x in itertools.product(range(2), range(2), range(width)):
        p = probs[b, :, y, x].tolist()
        by_hand = [
            sum(cost[j, k].item() * p[k] / priors[k].item() for k in range(3)) for j in range(3)
        ]
        assert got[b, :, y, x].tolist() == pytest.approx(by_hand, rel=1e-12)
    assert torch.equal(got.argmin(1), decide_reference(probs, cost, priors))
