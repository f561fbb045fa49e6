"""The compiled single-rule kernel (``costseg.decision.cpu.sparse_rule``, path ``numba``)
against the float64 reference.

``decide`` chooses it for CPU images of ``COMPILED_MIN_PIXELS`` pixels and more; here it is
forced for every image, including sizes that are not whole blocks of pixels. (The property-based
tests of tests/test_decision.py run through it too.)
"""

import numpy as np
import pytest
import torch
from decision_inputs import LOW_PRECISION, VERTICES, near_ties, smooth

from costseg.costs import load_cost
from costseg.decision import decide_reference
from costseg.decision.api import decide
from costseg.decision.certificate import reference_eps
from costseg.decision.certified import CertifiedCosts
from costseg.decision.cpu.row_groups import shared_rows
from costseg.decision.cpu.sparse_kernel import BLOCK
from costseg.decision.cpu.sparse_rule import SparseRule
from costseg.decision.dispatch import ENV
from costseg.decision.reference import shift

reference = decide_reference


@pytest.fixture(autouse=True)
def compiled(monkeypatch):
    monkeypatch.setenv(ENV, "numba")


def tensor_path(probs, cost, priors=None):
    """``decide`` on matmuls and ``certified.top``."""
    return decide(probs, cost, priors, path="torch")


def test_the_kernel_decides_and_certifies_most_pixels(monkeypatch):
    calls = []
    chunk = SparseRule.chunk
    monkeypatch.setattr(SparseRule, "chunk", lambda self, *a: calls.append(1) or chunk(self, *a))
    probs = smooth((1, 19, 64, 80), 0)
    assert torch.equal(decide(probs, VERTICES[2]), reference(probs, VERTICES[2]))
    assert calls
    for cost in VERTICES:
        cost = cost.double()[None]
        fast = CertifiedCosts(cost, probs, None, reference_eps(19, mixtures=False))
        rule = SparseRule(fast, cost, shift(cost))
        labels = torch.empty(64 * 80, dtype=torch.long)
        assert not len(rule.chunk(probs[0].view(19, -1), labels))  # open: the reference here
        assert torch.equal(labels, reference(probs, cost[0]).view(-1))
        rule.reference64 = None  # open pixels returned
        opened = rule.chunk(probs[0].view(19, -1), labels)
        assert len(opened) < 0.01 * len(labels), len(opened)


@pytest.mark.parametrize("dtype", [*LOW_PRECISION, torch.float64])
@pytest.mark.parametrize("name", ["robotistic", "altruistic", "egoistic"])
def test_paper_matrices_with_priors(name, dtype):
    cost = load_cost(name)
    shape = (2, 19, 37, 53)  # 1961 pixels: three blocks of 512 and a part
    for probs in (smooth(shape, 0, scale=12).to(dtype), smooth(shape, 1, scale=1).to(dtype)):
        assert torch.equal(decide(probs, cost), reference(probs, cost))
        gen = torch.Generator().manual_seed(2)
        for priors in (torch.rand(19, generator=gen) + 1e-5, torch.rand(19, 37, 53) + 1e-5):
            assert torch.equal(decide(probs, cost, priors), reference(probs, cost, priors))


@pytest.mark.parametrize("name", ["robotistic", "altruistic", "egoistic"])
def test_near_ties_within_float32_ulps(name):
    cost = load_cost(name)
    probs = near_ties(cost.double(), 1500, seed=4)
    expected = reference(probs, cost)
    assert torch.equal(decide(probs, cost), expected)
    assert (expected.view(-1, 7) != expected.view(-1, 7)[:, :1]).any()


@pytest.mark.parametrize("n", [2, 3, 5, 19])
def test_random_and_sparse_matrices_near_ties(n):
    """Dense random matrices, and matrices like the paper's: ones off the diagonal and a few
    large costs (E sparse, with large and small magnitudes in one row)."""
    gen = torch.Generator().manual_seed(n)
    for sparse in (False, True):
        for _ in range(5):
            cost = torch.rand(n, n, generator=gen, dtype=torch.float64) * 3 + 0.1
            if sparse:
                large = torch.rand(n, n, generator=gen, dtype=torch.float64) < 0.15
                cost = 1 + large * cost * 300
            cost.fill_diagonal_(0)
            probs = near_ties(cost, 150, seed=int(torch.randint(1 << 30, (1,), generator=gen)))
            assert torch.equal(decide(probs, cost), reference(probs, cost))


@pytest.mark.parametrize("n", [7, 19, 30])
def test_matrices_with_groups_of_rows_near_ties(n):
    """Three groups of rows, each sharing one random row but the diagonal (a group's shared
    sum, each row's own rest), and duplicated rows (no rest of their own: exact ties), with near
    ties."""
    gen = torch.Generator().manual_seed(n)
    for _ in range(4):
        kinds = torch.rand(3, n, generator=gen, dtype=torch.float64) * 300 + 1
        cost = kinds[torch.arange(n) % 3]
        cost.fill_diagonal_(0)
        cost[-1] = cost[-4]  # a duplicate
        sparse = cost - cost.mode(0, keepdim=True).values
        group = shared_rows(sparse.numpy())[0]
        assert (group >= 0).sum() >= n // 3, group  # the grouped path is taken
        probs = near_ties(cost, 150, seed=int(torch.randint(1 << 30, (1,), generator=gen)))
        assert torch.equal(decide(probs, cost), reference(probs, cost))


def test_rows_of_the_egoistic_matrix_grouped():
    """Its seven static classes share their entries but the diagonal: one group, one own term
    each; every row is its group's shared entries plus its own."""
    cost = load_cost("egoistic").double()
    sparse = (cost - cost.mode(0, keepdim=True).values).numpy()
    group, shared = shared_rows(sparse)
    static = [2, 3, 4, 5, 8, 17, 18]
    assert len(set(group[static].tolist())) == 1 and group[static[0]] >= 0
    own = sparse - np.where(group[:, None] >= 0, shared[group], 0)
    assert (np.count_nonzero(own[static], 1) == 1).all()
    terms = np.count_nonzero(shared) + np.count_nonzero(own)
    assert terms < np.count_nonzero(sparse) / 2, terms


def test_costs_from_tiny_to_huge_and_degenerate_matrices():
    probs = torch.cat([smooth((1, 4, 20, 30), 5), smooth((1, 4, 20, 30), 6, scale=0.5)])
    huge = torch.tensor(
        [[0, 1e30, 1e-30, 1], [1e-30, 0, 1e30, 1], [1, 1, 0, 1e-30], [1e30, 1e-30, 1, 0]]
    )
    zero_row = torch.ones(4, 4).fill_diagonal_(0)
    zero_row[2] = 0  # a row equal to its columns' most frequent entries... but for its own
    for cost in (huge, huge.T.contiguous(), torch.zeros(4, 4), torch.ones(4, 4), zero_row):
        assert torch.equal(decide(probs, cost), reference(probs, cost)), cost
    assert (decide(probs, torch.zeros(4, 4)) == 0).all()  # all costs tie: the lowest class


def test_exact_ties_underflow_and_non_finite_probabilities():
    probs = smooth((1, 19, 30, 40), 7)
    probs[0, :, 0, :5] = 1 / 19  # exact ties
    probs[0, :, 1, :5] = 1e-40  # subnormal in float32: costs underflow
    probs[0, :, 2, :5] = 0.0
    for cost in VERTICES:
        assert torch.equal(decide(probs, cost), reference(probs, cost))
    probs[0, 3, 3, :3] = torch.tensor([float("nan"), float("inf"), 0.0])
    probs[0, :, 4, 0] = float("inf")
    for cost in VERTICES:
        assert torch.equal(decide(probs, cost), tensor_path(probs, cost))


# one pixel, 15, one block, two blocks and a pixel
SHAPES = [(1, 19, 1, 1), (3, 19, 3, 5), (1, 19, 1, BLOCK), (2, 19, 1, 2 * BLOCK + 1)]


@pytest.mark.parametrize("shape", SHAPES)
def test_sizes_around_a_block(shape):
    probs = smooth(shape, 8, scale=3)
    for cost in VERTICES:
        assert torch.equal(decide(probs, cost), reference(probs, cost))
    assert torch.equal(decide(probs, None), probs.argmax(1))
