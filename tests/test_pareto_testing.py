"""Pareto Testing against a brute-force implementation written from the paper's algorithm
(Laufer-Goldshtein et al. 2023, Algorithm 1: Pareto front on D1, order by the largest p-value on
D1, fixed-sequence testing of ``max_i p_i`` on D2), the front against a dominance loop, the
guarantee by simulation, and the needed-size answer against the p-value at n and n − 1."""

from __future__ import annotations

import math

import numpy as np
import pytest

from costseg.calibration.guarantee import hoeffding_bentkus_pvalue
from costseg.calibration.pareto_testing import (
    choose,
    images_needed,
    pareto_front,
    pareto_testing,
)


def brute_front(values: np.ndarray) -> list[int]:
    """Indices no other point dominates (≤ everywhere, < somewhere), NaN as +inf."""
    v = [[math.inf if math.isnan(x) else x for x in row] for row in values.tolist()]
    front = []
    for i, a in enumerate(v):
        dominated = False
        for j, b in enumerate(v):
            pairs = list(zip(a, b, strict=True))
            if j != i and all(y <= x for x, y in pairs) and any(y < x for x, y in pairs):
                dominated = True
        if not dominated:
            front.append(i)
    return front


def binomial_cdf(k: int, n: int, p: float) -> float:
    return math.fsum(math.comb(n, j) * p**j * (1 - p) ** (n - j) for j in range(min(k, n) + 1))


def brute_hb(losses: list[float], alpha: float) -> tuple[float, int, float]:
    """(risk, n, Hoeffding–Bentkus p-value) of ``H: R > α`` over the defined losses, by hand:
    ``min(exp(−n h₁(R̂ ∧ α, α)), e · P(Bin(n, α) ≤ ⌈n R̂⌉))``."""
    defined = [x for x in losses if not math.isnan(x)]
    n = len(defined)
    if n == 0:
        return math.nan, 0, 1.0
    total = math.fsum(defined)
    risk = total / n
    a = min(risk, alpha)
    h1 = (a * math.log(a / alpha) if a > 0 else 0.0) + (1 - a) * math.log((1 - a) / (1 - alpha))
    bentkus = math.e * binomial_cdf(math.ceil(round(total, 9)), n, alpha)
    return risk, n, min(math.exp(-n * h1), bentkus, 1.0)


def brute_pareto_testing(d1, d2, alphas, delta, objective, maximize):
    """The paper's algorithm, loop by loop: (front, order, certified)."""
    _, count, k = d1.shape
    p1 = [[brute_hb(d1[:, c, i].tolist(), alphas[i])[2] for i in range(k)] for c in range(count)]
    p2 = [[brute_hb(d2[:, c, i].tolist(), alphas[i])[2] for i in range(k)] for c in range(count)]
    risks = np.array(
        [[brute_hb(d1[:, c, i].tolist(), alphas[i])[0] for i in range(k)] for c in range(count)]
    )
    signed = [0.0] * count
    points = risks
    if objective is not None:
        signed = [(-1 if maximize else 1) * x for x in objective]
        signed = [math.inf if math.isnan(x) else x for x in signed]
        points = np.column_stack([risks, signed])
    front = brute_front(points)
    order = sorted(front, key=lambda c: (max(p1[c]), signed[c], c))
    certified = []
    for c in order:
        if max(p2[c]) > delta:
            break
        certified.append(c)
    return front, order, certified


def test_front_against_a_dominance_loop_with_ties_duplicates_and_nan() -> None:
    rng = np.random.default_rng(0)
    for trial in range(60):
        size, dims = int(rng.integers(1, 40)), int(rng.integers(1, 5))
        values = rng.integers(0, 4, size=(size, dims)).astype(float)  # many ties
        if trial % 3 == 0:
            values[rng.random(values.shape) < 0.1] = np.nan
        if size > 2:
            values[1] = values[0]  # an exact duplicate
        assert pareto_front(values).tolist() == brute_front(values)


def test_pareto_testing_against_the_papers_algorithm() -> None:
    rng = np.random.default_rng(1)
    certified_sizes = set()
    for trial in range(40):
        count, k = int(rng.integers(1, 25)), int(rng.integers(1, 4))
        n1, n2 = int(rng.integers(20, 120)), int(rng.integers(20, 120))
        alphas = rng.uniform(0.05, 0.3, k)
        risks = rng.uniform(0, 0.35, (count, k))
        d1 = (rng.random((n1, count, k)) < risks).astype(float)
        d2 = (rng.random((n2, count, k)) < risks).astype(float)
        if trial % 4 == 1:  # continuous losses, e.g. 1 − recall of an image
            d1, d2 = d1 * rng.random(d1.shape), d2 * rng.random(d2.shape)
        if trial % 2 == 0:  # undefined losses (no such pixels in an image)
            d1[rng.random(d1.shape) < 0.2] = np.nan
            d2[rng.random(d2.shape) < 0.2] = np.nan
        objective = None if trial % 5 == 0 else rng.integers(0, 5, count).astype(float)
        maximize = bool(trial % 3)
        delta = float(rng.choice([0.05, 0.1, 0.2]))
        result = pareto_testing(d1, d2, alphas, delta, objective, maximize)
        front, order, certified = brute_pareto_testing(d1, d2, alphas, delta, objective, maximize)
        assert result.front.tolist() == front
        assert result.order.tolist() == order
        assert result.certified.tolist() == certified
        certified_sizes.add(min(len(certified), 2))
        for c in range(count):
            for i in range(k):
                risk, n, p = brute_hb(d2[:, c, i].tolist(), alphas[i])
                assert result.n_d2[c, i] == n and result.pvalues_d2[c, i] == pytest.approx(p)
                assert result.risks_d2[c, i] == pytest.approx(risk, nan_ok=True)
        if certified:
            assert result.best is None and result.needed_n is None
        else:
            excess = [  # the front's candidate closest to meeting every constraint on D1
                max(_excess(brute_hb(d1[:, c, i].tolist(), alphas[i])[0], alphas[i])
                    for i in range(k))
                for c in order
            ]  # fmt: skip
            best = order[excess.index(min(excess))]
            assert result.best == best
            assert result.failed == int(np.argmax(result.pvalues_d2[best]))
    assert certified_sizes == {0, 1, 2}  # none, one and several certified all occur


def _excess(risk: float, alpha: float) -> float:
    return math.inf if math.isnan(risk) else risk - alpha


def test_choose_is_the_best_certified_objective_first_of_ties() -> None:
    rng = np.random.default_rng(2)
    for _ in range(30):
        count = int(rng.integers(2, 15))
        d = (rng.random((200, count, 2)) < rng.uniform(0, 0.2, (count, 2))).astype(float)
        result = pareto_testing(d[:100], d[100:], [0.15, 0.15], 0.1)
        objective = rng.integers(0, 3, count).astype(float)
        for maximize in (True, False):
            want = None
            for c in result.certified.tolist():
                better = (
                    objective[c] > objective[want] if maximize else objective[c] < objective[want]
                )
                if want is None or better:
                    want = c
            assert choose(result, objective, maximize) == want


def test_the_guarantee_by_simulation() -> None:
    """Fixed per-image losses of 64 candidates with known true risks; over many random D1 / D2
    draws the share whose certified candidates include one with a true risk above some α_i is at
    most δ + 3 s.e., while choosing on the empirical risks alone violates far more often."""
    rng = np.random.default_rng(4)
    population, alphas, delta, n1, n2, splits = 20_000, np.array([0.1, 0.1]), 0.1, 150, 150, 400
    grid = np.linspace(0.03, 0.16, 8)
    targets = np.array([(a, b) for a in grid for b in grid])  # (64, 2)
    latent = rng.random((population, 1, 2))
    losses = (latent < targets[None]).astype(np.float32)  # nested: monotone in the target
    true_risk = losses.mean(axis=0)
    violates = (true_risk > alphas).any(axis=1)
    objective_pool = losses.sum(axis=2)  # higher = closer to the limits (like "change least")
    bad, naive_bad, certified_any = 0, 0, 0
    for _ in range(splits):
        draw = rng.integers(0, population, n1 + n2)  # i.i.d. from the population
        d1, d2 = losses[draw[:n1]], losses[draw[n1:]]
        result = pareto_testing(d1, d2, alphas, delta, objective_pool[draw[:n1]].mean(axis=0))
        bad += bool(violates[result.certified].any())
        certified_any += len(result.certified) > 0
        chosen = choose(result, objective_pool[draw].mean(axis=0))
        assert chosen is None or chosen in result.certified
        empirical = losses[draw].mean(axis=0)
        feasible = np.flatnonzero((empirical <= alphas).all(axis=1))
        naive = feasible[np.argmax(objective_pool[draw].mean(axis=0)[feasible])]
        naive_bad += bool(violates[naive])
    error = math.sqrt(delta * (1 - delta) / splits)
    assert bad / splits <= delta + 3 * error
    assert certified_any / splits > 0.5  # not vacuous
    assert naive_bad / splits > delta + 3 * error  # the simulation can see a violation


def test_needed_size_is_the_first_passing_n() -> None:
    for risk, alpha, delta in [(0.0, 0.05, 0.1), (0.02, 0.05, 0.1), (0.07, 0.1, 0.05),
                               (0.1, 0.3, 0.2), (0.123, 0.15, 0.1)]:  # fmt: skip
        n = images_needed(risk, alpha, delta)
        assert hoeffding_bentkus_pvalue(risk, n, alpha) <= delta
        passing = hoeffding_bentkus_pvalue(risk, np.arange(1, n), alpha) <= delta
        assert not passing.any() and hoeffding_bentkus_pvalue(risk, n - 1, alpha) > delta
    assert images_needed(0.1, 0.1, 0.1) is None
    assert images_needed(0.0999999, 0.1, 0.1, limit=1000) > 1000  # Hoeffding's size


def test_nothing_certified_is_a_result_with_the_size_needed() -> None:
    rng = np.random.default_rng(5)
    risks = np.array([[0.04, 0.06], [0.3, 0.01]])
    d1 = (rng.random((400, 2, 2)) < risks).astype(float)
    d2 = np.zeros((15, 2, 2))  # too few images for α = 0.1 at δ = 0.1 (22 at a zero risk)
    d2[0, 0, 0] = 1
    d2[:5, :, 1] = np.nan
    result = pareto_testing(d1, d2, [0.1, 0.1], 0.1)
    assert result.certified.tolist() == [] and result.best == 0
    failed = result.failed
    assert result.pvalues_d2[0, failed] == result.pvalues_d2[0].max() > 0.1
    observed = result.risks_d2[0, failed]
    n = result.needed_n
    assert hoeffding_bentkus_pvalue(observed, n, 0.1) <= 0.1
    assert hoeffding_bentkus_pvalue(observed, n - 1, 0.1) > 0.1
    share = result.n_d2[0, failed] / 15
    assert result.needed_images == math.ceil(n / share)


def test_invalid_inputs_are_refused() -> None:
    ok = np.zeros((10, 3, 2))
    for args, match in [
        ((ok, np.zeros((10, 4, 2)), [0.1, 0.1], 0.1), "losses must be"),
        ((ok, ok, [0.1], 0.1), "alphas must give"),
        ((ok, ok, [0.1, 1.0], 0.1), "alphas must lie"),
        ((ok, ok, [0.1, 0.1], 0.0), "delta"),
        ((ok + 2, ok, [0.1, 0.1], 0.1), r"\[0, 1\]"),
    ]:
        with pytest.raises(ValueError, match=match):
            pareto_testing(*args)
    with pytest.raises(ValueError, match="objective_d1"):
        pareto_testing(ok, ok, [0.1, 0.1], 0.1, objective_d1=[1.0])


def test_the_split_is_random_seeded_and_covers_every_image_once() -> None:
    """D1 and D2 (docs/definitions.md §20): disjoint, together every image, half each; the same
    seed draws the same split, another seed another; not the halves in order."""
    from costseg.calibration.pareto_testing import split_images

    for n in (0, 1, 7, 100):
        d1, d2 = split_images(n, seed=5)
        assert len(d1) == n // 2 and not set(d1.tolist()) & set(d2.tolist())
        assert sorted([*d1.tolist(), *d2.tolist()]) == list(range(n))
        assert list(d1) == sorted(d1) and list(d2) == sorted(d2)
    same = [split_images(100, seed=s)[0].tolist() for s in (5, 5, 6)]
    assert same[0] == same[1] and same[0] != same[2]
    assert same[0] != list(range(50))  # not the first half
    firsts = np.mean([np.mean(split_images(100, seed=s)[0] < 50) for s in range(50)])
    assert 0.4 < firsts < 0.6  # D1 draws from both halves alike
