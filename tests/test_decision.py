"""decide and decide_mixtures, on every CPU path (forced), against decide_reference.

The inputs aim at the places where float32 cannot decide: exact ties, ties within a few float32
ulps, low-precision probabilities and costs spanning 0.1 to 1000 (tests/decision_inputs.py).
"""

import pytest
import torch
from decision_inputs import (
    CPU_PATHS,
    LOW_PRECISION,
    VERTICES,
    ml_cost,
    near_ties,
    probabilities,
    smooth,
)
from hypothesis import given, settings
from hypothesis import strategies as st

from costseg.costs import barycentric_grid, load_cost, mix_costs, symmetric_cost
from costseg.decision import (
    decide,
    decide_mixtures,
    decide_mixtures_reference,
    decide_reference,
)
from costseg.decision.dispatch import ENV
from costseg.decision.label_maps import empty_labels


@pytest.fixture(params=CPU_PATHS)
def forced(request, monkeypatch):
    """Each CPU path, forced for every decide and decide_mixtures call of the test."""
    monkeypatch.setenv(ENV, request.param)
    return request.param


@pytest.mark.parametrize("path", CPU_PATHS)
@settings(max_examples=100, deadline=None)
@given(probabilities(), st.floats(0.01, 100))
def test_symmetric_rule_is_argmax_including_ties(path, probs, lam):
    cost = lam * symmetric_cost(probs.shape[1])
    assert torch.equal(decide(probs, cost, path=path), probs.argmax(1))
    assert torch.equal(decide(probs, None, path=path), probs.argmax(1))


@pytest.mark.parametrize("path", CPU_PATHS)
@settings(max_examples=100, deadline=None)
@given(probabilities(), st.floats(1e-3, 1e3), st.integers(0, 2**31))
def test_scale_invariance(path, probs, mu, seed):
    n = probs.shape[1]
    gen = torch.Generator().manual_seed(seed)
    cost = (torch.rand(n, n, generator=gen) + 0.1) * (1 - torch.eye(n))
    assert torch.equal(decide(probs, mu * cost, path=path), decide(probs, cost, path=path))


@pytest.mark.parametrize("path", CPU_PATHS)
@settings(max_examples=100, deadline=None)
@given(probabilities(), st.integers(0, 2**31), st.booleans())
def test_random_costs_and_priors_match_the_reference(path, probs, seed, pixelwise):
    _, n, h, w = probs.shape
    gen = torch.Generator().manual_seed(seed)
    cost = torch.randint(1, 5, (n, n), generator=gen).double() * (1 - torch.eye(n))
    assert torch.equal(decide(probs, cost, path=path), decide_reference(probs, cost))
    priors = torch.randint(1, 4, (n, h, w) if pixelwise else (n,), generator=gen) / 4
    got = decide(probs, cost, priors, path=path)
    assert torch.equal(got, decide_reference(probs, cost, priors))


@pytest.mark.parametrize("dtype", LOW_PRECISION)
@pytest.mark.parametrize("name", ["altruistic", "egoistic"])
def test_paper_matrices_match_the_reference(name, dtype, forced):
    cost = load_cost(name)
    sharp = smooth((2, 19, 48, 64), 0, scale=12).to(dtype)
    flat = smooth((1, 19, 48, 64), 1, scale=1).to(dtype)
    gen = torch.Generator().manual_seed(11)
    logits = torch.randn(2, 19, 64, 80, generator=gen) * torch.rand(2, 1, 64, 80, generator=gen)
    mixed = (logits * 8).softmax(1).to(dtype)  # bfloat16: many exact float64 ties
    for probs in (sharp, flat, mixed):
        assert torch.equal(decide(probs, cost), decide_reference(probs, cost))
    priors = torch.rand(19, 48, 64, generator=torch.Generator().manual_seed(2)) + 1e-5
    assert torch.equal(decide(flat, cost, priors), decide_reference(flat, cost, priors))
    pri = priors[:, 0, 0]
    assert torch.equal(decide(flat, cost, pri), decide_reference(flat, cost, pri))


@pytest.mark.parametrize("name", ["robotistic", "altruistic", "egoistic"])
def test_near_ties_within_float32_ulps(name, forced):
    cost = load_cost(name)
    probs = near_ties(cost, 1500, seed=3)
    expected = decide_reference(probs, cost)
    assert torch.equal(decide(probs, cost), expected)
    # The construction does produce decisions that flip within a few ulps.
    assert (expected.view(-1, 7) != expected.view(-1, 7)[:, :1]).any()


@pytest.mark.parametrize("n", [2, 3])
def test_few_classes_near_ties(n, forced):
    """Few classes: few index bits, so the rounding bound itself must catch the near ties."""
    gen = torch.Generator().manual_seed(n)
    for _ in range(20):
        cost = (torch.rand(n, n, generator=gen, dtype=torch.float64) * 3 + 0.1).fill_diagonal_(0)
        probs = near_ties(cost, 140, seed=int(torch.randint(1 << 30, (1,), generator=gen)))
        assert torch.equal(decide(probs, cost), decide_reference(probs, cost))
        vertices = (torch.rand(3, n, n, generator=gen, dtype=torch.float64) * 3 + 0.1).clone()
        for v in vertices:
            v.fill_diagonal_(0)
        weights = barycentric_grid(0.1)
        probs = near_ties(mix_costs(vertices, weights)[30], 140, seed=n)
        loop = decide_mixtures_reference(probs, vertices, weights)
        assert torch.equal(decide_mixtures(probs, vertices, weights).long(), loop)


def test_costs_spanning_fourteen_orders_of_magnitude(forced):
    """Two tiny costs near a tie next to huge columns: the float64 reference's own rounding
    (relative to the huge shifted costs) decides there, and the fast path must follow it."""
    gen = torch.Generator().manual_seed(12)
    cost = torch.tensor([[0, 3e-7, 1e-7], [7e-7, 0, 1e-7], [1e7, 1e7, 0]], dtype=torch.float64)
    q0 = torch.rand(20000, generator=gen, dtype=torch.float64) * 1e-3 + 1e-3
    q1 = q0 * 7 / 3 * (1 + (torch.rand(20000, generator=gen, dtype=torch.float64) - 0.5) * 2e-3)
    probs = torch.stack([q0, q1, 1 - q0 - q1]).float().view(1, 3, 100, 200)
    assert torch.equal(decide(probs, cost), decide_reference(probs, cost))
    weights = barycentric_grid(0.25)
    vertices = torch.stack([cost, cost.T.contiguous(), symmetric_cost(3)])
    loop = decide_mixtures_reference(probs, vertices, weights)
    assert torch.equal(decide_mixtures(probs, vertices, weights).long(), loop)


def test_exact_ties(forced):
    uniform = torch.full((1, 19, 2, 2), 1 / 19)
    assert (decide(uniform, None) == 0).all()
    # Wall (3) and fence (4) are both "static": with p_wall = p_fence their costs tie in exact
    # arithmetic under every preset; the reference's float64 sums decide, the fast path follows.
    probs = torch.zeros(1, 19, 1, 3)
    probs[0, [3, 4], 0, :] = 0.4
    probs[0, [0, 11, 13], 0, [0, 1, 2]] = 0.2
    for cost in VERTICES:
        assert torch.equal(decide(probs, cost), decide_reference(probs, cost))
    assert (decide(probs, VERTICES[0]) == 3).all()
    for dtype in (torch.float16, torch.bfloat16):
        ties = uniform.to(dtype)
        for cost in VERTICES:
            assert torch.equal(decide(ties, cost), decide_reference(ties, cost))


@pytest.mark.parametrize("pixelwise", [False, True])
def test_ml_is_argmax_of_p_over_prior(pixelwise, forced):
    gen = torch.Generator().manual_seed(1)
    probs = torch.rand(2, 19, 16, 24, generator=gen).softmax(1)
    shape = (19, 16, 24) if pixelwise else (19,)
    priors = torch.rand(shape, generator=gen) + 0.01
    priors = priors / priors.sum(0)
    view = priors.double() if pixelwise else priors.double().view(19, 1, 1)
    expected = (probs.double() / view).argmax(1)
    assert torch.equal(decide(probs, None, priors=priors), expected)
    if not pixelwise:  # the global ML matrix λ/π gives the same decisions
        assert torch.equal(decide(probs, ml_cost(priors)), expected)


def test_prior_adapted_rule_matches_the_reference(forced):
    probs = smooth((1, 19, 20, 30), 4, scale=3)
    priors = torch.rand(19, 20, 30, generator=torch.Generator().manual_seed(5)) + 0.05
    adapted = 0.6 + 0.4 * priors / priors.sum(0)
    cost = VERTICES[1]
    assert torch.equal(decide(probs, cost, adapted), decide_reference(probs, cost, adapted))


def test_chunks_larger_than_one_and_batch_order(forced):
    probs = smooth((3, 19, 200, 210), 6)  # more than one CPU chunk per image
    assert torch.equal(decide(probs, None), probs.argmax(1))
    expected = torch.stack([decide(probs[i : i + 1], VERTICES[2])[0] for i in range(3)])
    assert torch.equal(decide(probs, VERTICES[2]), expected)
    assert torch.equal(expected, decide_reference(probs, VERTICES[2]))


def loop_of_decides(probs, weights, priors=None):
    return decide_mixtures_reference(probs, VERTICES, weights, priors)


def test_mixtures_equal_decide_on_each_mixed_matrix(forced):
    weights = barycentric_grid(0.1)
    probs = torch.cat([smooth((1, 19, 40, 48), 7), smooth((1, 19, 40, 48), 8, scale=1)])
    assert torch.equal(
        decide_mixtures(probs, VERTICES, weights).long(), loop_of_decides(probs, weights)
    )
    for priors in (torch.rand(19, 40, 48) + 0.01, torch.rand(19) + 0.01):
        mixed = decide_mixtures(probs, VERTICES, weights, priors).long()
        assert torch.equal(mixed, loop_of_decides(probs, weights, priors))


@pytest.mark.parametrize("dtype", LOW_PRECISION)
def test_mixtures_on_ties_and_low_precision(dtype, forced):
    weights = barycentric_grid(0.1)
    probs = torch.cat([smooth((1, 19, 24, 24), 9, scale=2), torch.full((1, 19, 24, 24), 1 / 19)])
    probs = probs.to(dtype)
    assert torch.equal(
        decide_mixtures(probs, VERTICES, weights).long(), loop_of_decides(probs, weights)
    )


def test_mixtures_near_ties_of_a_mixed_matrix(forced):
    weights = barycentric_grid(0.1)
    for k in (12, 40):  # ties constructed on one grid point's matrix
        probs = near_ties(mix_costs(VERTICES, weights)[k], 700, seed=k)
        mixed = decide_mixtures(probs, VERTICES, weights).long()
        assert torch.equal(mixed, loop_of_decides(probs, weights))


def test_mixtures_on_non_finite_probabilities(forced):
    probs = smooth((1, 19, 12, 12), 11)
    probs[0, 3, 0, :4] = torch.tensor([float("nan"), float("inf"), 0.0, 0.0])
    probs[0, :, 1, 0] = float("inf")
    weights = barycentric_grid(0.1)
    assert torch.equal(
        decide_mixtures(probs, VERTICES, weights).long(), loop_of_decides(probs, weights)
    )


def test_mixture_vertices_are_the_single_rules(forced):
    probs = torch.cat([torch.full((1, 19, 3, 3), 1 / 19), smooth((1, 19, 3, 3), 10)])
    labels = decide_mixtures(probs, VERTICES, torch.eye(3, dtype=torch.float64))
    for v in range(3):
        assert torch.equal(labels[:, v].long(), decide(probs, VERTICES[v]))
    assert (labels[0, 0] == 0).all()


def test_bad_inputs():
    with pytest.raises(ValueError, match=r"probs must be a float \(B, N, H, W\)"):
        decide(torch.rand(19, 4, 4), None)
    with pytest.raises(ValueError, match="cost matrix must be 19x19 for 19 classes"):
        decide(torch.rand(1, 19, 4, 4), torch.ones(3, 3))
    with pytest.raises(ValueError, match=r"priors must be \(19,\) or \(19, 4, 4\)"):
        decide(torch.rand(1, 19, 4, 4), None, priors=torch.ones(19, 2, 2))
    with pytest.raises(ValueError, match="priors must be > 0"):
        decide(torch.rand(1, 19, 4, 4), None, priors=torch.zeros(19))
    with pytest.raises(ValueError, match=r"weights \(K, V\)"):
        decide_mixtures(torch.rand(1, 19, 4, 4), VERTICES, torch.ones(5, 2))
    with pytest.raises(ValueError, match="weights must be >= 0"):
        decide_mixtures(torch.rand(1, 19, 4, 4), VERTICES, torch.tensor([[1.0, -0.5, 0.5]]))
    with pytest.raises(ValueError, match="weights must be >= 0"):
        decide_mixtures(torch.rand(1, 19, 4, 4), VERTICES, torch.zeros(1, 3))


def test_decisions_ignore_autocast():
    """Validation runs under bf16 autocast: the decision layer keeps its own precision."""
    probs = torch.rand(2, 19, 16, 24, generator=torch.Generator().manual_seed(3)).softmax(1)
    vertices = torch.stack([load_cost(n) for n in ("robotistic", "altruistic", "egoistic")])
    grid = barycentric_grid(0.25)
    plain = decide(probs, vertices[2]), decide_mixtures(probs, vertices, grid)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        autocast = decide(probs, vertices[2]), decide_mixtures(probs, vertices, grid)
    assert torch.equal(plain[0], autocast[0]) and torch.equal(plain[1], autocast[1])


def test_matrices_and_weights_that_require_grad_decide_the_same():
    # The prepared matrices are cached by their bytes: tensors in an autograd graph must work too.
    probs, weights = smooth((1, 19, 6, 8), 8), barycentric_grid(0.5)
    grad_v, grad_w = VERTICES.clone().requires_grad_(True), weights.clone().requires_grad_(True)
    assert torch.equal(decide(probs, grad_v[2]), decide(probs, VERTICES[2]))
    got = decide_mixtures(probs, grad_v, grad_w)
    assert torch.equal(got, decide_mixtures(probs, VERTICES, weights))


def test_label_maps_have_the_asked_shape_and_type():
    labels = empty_labels(2, 3, dtype=torch.uint8, device="cpu")
    labels.fill_(7)
    assert labels.shape == (2, 3) and labels.dtype == torch.uint8 and int(labels.sum()) == 42
    assert empty_labels(4, dtype=torch.int64, device="cpu").dtype == torch.int64
    assert empty_labels(4, dtype=torch.float32, device="cpu").dtype == torch.float32  # torch's
