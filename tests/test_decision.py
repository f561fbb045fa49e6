"""The decision layer against brute-force references."""

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from costseg.costs import barycentric_grid, load_cost, mix_costs, ml_cost
from costseg.decision import DecisionLayer, decide, decide_mixtures

VERTICES = torch.stack([load_cost(n) for n in ("robotistic", "altruistic", "egoistic")])


def brute_force(probs, cost, priors=None):
    """The definition, one pixel at a time: argmin_k' Σ_k C[k',k] p_k/π_k, first index on ties."""
    b, n, h, w = probs.shape
    out = torch.empty(b, h, w, dtype=torch.long)
    for i in range(b):
        for y in range(h):
            for x in range(w):
                q = probs[i, :, y, x].double()
                if priors is not None:
                    q = q / (priors if priors.ndim == 1 else priors[:, y, x]).double()
                costs = [sum(cost[j, k].item() * q[k].item() for k in range(n)) for j in range(n)]
                out[i, y, x] = min(range(n), key=lambda j: (costs[j], j))
    return out


@st.composite
def probabilities(draw, max_classes=6):
    """Random probabilities with many exact ties: values drawn from a few levels."""
    n = draw(st.integers(2, max_classes))
    b, h, w = draw(st.integers(1, 2)), draw(st.integers(1, 4)), draw(st.integers(1, 4))
    levels = draw(st.lists(st.sampled_from([0.0, 0.1, 0.25, 0.5, 1.0, 3.0]), min_size=1))
    raw = draw(st.lists(st.sampled_from(levels), min_size=b * n * h * w, max_size=b * n * h * w))
    raw = torch.tensor(raw, dtype=torch.float32).view(b, n, h, w) + 1e-3
    dtype = draw(st.sampled_from([torch.float32, torch.float16, torch.bfloat16]))
    return (raw / raw.sum(1, keepdim=True)).to(dtype)


@settings(max_examples=200, deadline=None)
@given(probabilities(), st.floats(0.01, 100))
def test_symmetric_rule_is_argmax_including_ties(probs, lam):
    cost = lam * (1 - torch.eye(probs.shape[1]))
    assert torch.equal(decide(probs, cost), probs.argmax(1))
    assert torch.equal(decide(probs, None), probs.argmax(1))


@settings(max_examples=100, deadline=None)
@given(probabilities(), st.floats(1e-3, 1e3), st.integers(0, 2**31))
def test_scale_invariance(probs, mu, seed):
    n = probs.shape[1]
    gen = torch.Generator().manual_seed(seed)
    cost = (torch.rand(n, n, generator=gen) + 0.1) * (1 - torch.eye(n))
    assert torch.equal(decide(probs, mu * cost), decide(probs, cost))


@settings(max_examples=60, deadline=None)
@given(probabilities(), st.integers(0, 2**31))
def test_random_cost_matches_brute_force(probs, seed):
    n = probs.shape[1]
    gen = torch.Generator().manual_seed(seed)
    cost = torch.randint(1, 5, (n, n), generator=gen).double() * (1 - torch.eye(n))
    assert torch.equal(decide(probs, cost), brute_force(probs, cost))


def test_paper_presets_match_brute_force():
    probs = torch.rand(1, 19, 5, 6, generator=torch.Generator().manual_seed(0)).pow(4)
    probs = probs / probs.sum(1, keepdim=True)
    for cost in VERTICES:
        assert torch.equal(decide(probs, cost), brute_force(probs, cost))


@pytest.mark.parametrize("pixelwise", [False, True])
def test_ml_is_argmax_of_p_over_prior(pixelwise):
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


def test_prior_adapted_rule_matches_brute_force():
    gen = torch.Generator().manual_seed(2)
    probs = torch.rand(1, 19, 4, 5, generator=gen).pow(3)
    probs = probs / probs.sum(1, keepdim=True)
    priors = torch.rand(19, 4, 5, generator=gen) + 0.05
    alpha = 0.4
    adapted = (1 - alpha) + alpha * priors / priors.sum(0)
    cost = VERTICES[1]
    assert torch.equal(decide(probs, cost, adapted), brute_force(probs, cost, adapted))


@pytest.mark.parametrize("step", [0.1, 0.05])
def test_mixtures_equal_loop_over_mixed_matrices(step):
    gen = torch.Generator().manual_seed(3)
    # Sharp and flat pixels alike, so that pruning and full mixing are both exercised.
    probs = (
        torch.randn(2, 19, 24, 32, generator=gen) * torch.rand(2, 1, 24, 32, generator=gen) * 8
    ).softmax(1)
    weights = barycentric_grid(step)
    mixed = decide_mixtures(probs, VERTICES, weights)
    loop = torch.stack([decide(probs, c) for c in mix_costs(VERTICES, weights)], 1)
    assert torch.equal(mixed, loop)
    priors = torch.rand(19, 24, 32, generator=gen) + 0.01
    mixed = decide_mixtures(probs, VERTICES, weights, priors)
    loop = torch.stack([decide(probs, c, priors) for c in mix_costs(VERTICES, weights)], 1)
    assert torch.equal(mixed, loop)


def test_mixture_vertices_are_the_single_rules_with_ties():
    probs = torch.full((1, 19, 3, 3), 1 / 19)  # every class tied
    labels = decide_mixtures(probs, VERTICES, torch.eye(3, dtype=torch.float64))
    for v in range(3):
        assert torch.equal(labels[:, v], decide(probs, VERTICES[v]))
    assert (labels[:, 0] == 0).all()


def test_chunks_larger_than_one_and_batch_order():
    gen = torch.Generator().manual_seed(4)
    probs = torch.rand(3, 19, 130, 140, generator=gen).softmax(1)  # > one CPU chunk per image
    assert torch.equal(decide(probs, None), probs.argmax(1))
    expected = torch.stack([decide(probs[i : i + 1], VERTICES[2])[0] for i in range(3)])
    assert torch.equal(decide(probs, VERTICES[2]), expected)


def test_module_keeps_costs_out_of_the_state_dict():
    layer = DecisionLayer(VERTICES)
    assert layer.state_dict() == {}
    probs = torch.rand(1, 19, 6, 7).softmax(1)
    out = layer(probs)
    assert torch.equal(out[:, 2], decide(probs, VERTICES[2]))


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
