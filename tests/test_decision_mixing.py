"""The compiled mixture kernel (``costseg.decision.cpu.mixture_kernel``, path ``numba``)
against the reference on each mixed matrix: pixels with few candidates (slots), with many
(gathered groups), with more than the kernel holds (left open, re-checked), several chunks,
other numbers of vertices and classes."""

import pytest
import torch
from decision_inputs import VERTICES, near_ties, smooth

from costseg.costs import barycentric_grid, mix_costs
from costseg.decision import decide_mixtures, decide_mixtures_reference
from costseg.decision.certificate import reference_eps
from costseg.decision.certified import CertifiedCosts
from costseg.decision.cpu import VERTICES as MOST_VERTICES
from costseg.decision.cpu.mixer import CHUNK, NumbaMixer
from costseg.decision.cpu.mixture_kernel import GROUPS, SLOTS, WIDEST
from costseg.decision.tensor_ops import Mixer

loop = decide_mixtures_reference


def compiled(probs, vertices, weights, priors=None):
    return decide_mixtures(probs, vertices, weights, priors, path="numba").long()


def candidate_counts(probs, vertices, weights):
    """How many candidates each pixel has (``Mixer.candidates``), as the kernel counts them."""
    fast = CertifiedCosts(vertices.double(), probs, None, reference_eps(probs.shape[1], True))
    mix = Mixer(weights.double(), fast, mix_costs(vertices, weights))
    costs = fast.costs(fast.probs[0].float())
    return mix.candidates(costs, costs[:, :-1].argmin(1)).sum(0)


def random_vertices(count, n, seed, spread=3.0):
    gen = torch.Generator().manual_seed(seed)
    vertices = torch.rand(count, n, n, generator=gen, dtype=torch.float64) * spread + 0.1
    for v in vertices:
        v.fill_diagonal_(0)
    return vertices


def test_pixels_with_few_many_and_most_candidates():
    vertices = random_vertices(3, 19, 0)
    weights = barycentric_grid(0.1)
    probs = torch.cat([smooth((1, 19, 30, 40), 1, scale=4), smooth((1, 19, 30, 40), 2, scale=2)])
    counts = candidate_counts(probs[:1], vertices, weights)
    assert (counts <= SLOTS).any() and ((counts > SLOTS) & (counts <= GROUPS[0])).any()
    assert (counts > GROUPS[-1]).any()  # all three ways of mixing are used
    assert torch.equal(compiled(probs, vertices, weights), loop(probs, vertices, weights))


def test_more_classes_than_the_kernel_holds():
    n = WIDEST + 8  # pixels with more candidates than WIDEST are left open and re-checked
    vertices = random_vertices(3, n, 1)
    weights = barycentric_grid(0.25)
    noise = torch.rand(1, n, 6, 7, generator=torch.Generator().manual_seed(0))
    probs = 1.0 / n + noise * 0.1
    assert (candidate_counts(probs, vertices, weights) > WIDEST).any()
    assert torch.equal(compiled(probs, vertices, weights), loop(probs, vertices, weights))


@pytest.mark.parametrize("count", [1, 2, MOST_VERTICES, MOST_VERTICES + 1])
def test_other_numbers_of_vertices(count):
    """Up to VERTICES vertices the kernel pads with zero weights; more: tensor operations."""
    run = compiled if count <= MOST_VERTICES else decide_mixtures
    vertices = torch.cat([VERTICES, random_vertices(3, 19, count)])[:count]
    gen = torch.Generator().manual_seed(count)
    weights = torch.rand(count + 7, count, generator=gen, dtype=torch.float64)
    weights[0] = 0
    weights[0, 0] = 1  # a vertex itself
    probs = smooth((1, 19, 20, 24), count, scale=2)
    assert torch.equal(run(probs, vertices, weights).long(), loop(probs, vertices, weights))


def test_several_chunks_and_priors(monkeypatch):
    """A float32 image without pixel-wise priors is one chunk; float16 images and pixel-wise
    priors go chunk by chunk (here 3 chunks and a part per image)."""
    monkeypatch.setattr("costseg.decision.cpu.mixer.CHUNK", 1000)
    assert CHUNK > 1000
    weights = barycentric_grid(0.2)
    priors = torch.rand(19, generator=torch.Generator().manual_seed(3)) + 0.01
    for probs in (smooth((2, 19, 40, 83), 5, scale=4), smooth((1, 19, 40, 83), 6).half()):
        for pri in (None, priors, torch.rand(19, 40, 83) + 0.01):
            expected = loop(probs, VERTICES, weights, pri)
            assert torch.equal(compiled(probs, VERTICES, weights, pri), expected)


def test_near_ties_under_global_priors():
    """The kernel's float64 re-check folds global priors into its weights: pixels near a tie of
    one mixed matrix under priors are decided as decide decides them."""
    weights = barycentric_grid(0.1)
    priors = torch.rand(19, generator=torch.Generator().manual_seed(4), dtype=torch.float64)
    priors += 0.05
    probs = near_ties(mix_costs(VERTICES, weights)[25] / priors, 400, seed=25)
    expected = loop(probs, VERTICES, weights, priors)
    assert torch.equal(compiled(probs, VERTICES, weights, priors), expected)


def test_kernel_certifies_most_pairs():
    probs = smooth((1, 19, 64, 64), 6)
    weights = barycentric_grid(0.1)
    fast = CertifiedCosts(VERTICES.double(), probs, None, reference_eps(19, mixtures=True))
    mixed = mix_costs(VERTICES, weights)
    mixer = NumbaMixer(fast, weights.double(), Mixer(weights.double(), fast, mixed).gamma, mixed)
    labels = torch.empty(len(weights), 64 * 64, dtype=torch.uint8)
    grid, _ = mixer.chunk(fast.probs[0].float(), labels, 0)
    assert len(grid) < 0.01 * labels.numel(), len(grid)
