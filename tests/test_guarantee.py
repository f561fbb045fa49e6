"""Learn-then-Test: p-values against independent formulas, the family-wise error guarantee on
synthetic losses with known risks, and the per-image loss helpers."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy.stats import binom

from costseg.calibration.guarantee import (
    defined_risks,
    hoeffding_bentkus_pvalue,
    hoeffding_pvalue,
    learn_then_test,
)
from costseg.metrics.per_image import per_image_loss

# (successes k, images n, alpha): binary losses, so R̂ = k / n exactly in the reference.
CASES = [(0, 50, 0.2), (5, 50, 0.2), (3, 10, 0.5), (12, 100, 0.2), (30, 100, 0.1), (7, 7, 0.3)]


def reference_hb(k: int, n: int, alpha: float) -> float:
    """LTT's Hoeffding–Bentkus p-value written out with math and scipy.stats.binom."""
    a = min(k / n, alpha)
    h1 = (a * math.log(a / alpha) if a > 0 else 0.0) + (1 - a) * math.log((1 - a) / (1 - alpha))
    return min(math.exp(-n * h1), math.e * binom.cdf(k, n, alpha))


def test_hoeffding_against_formula() -> None:
    for k, n, alpha in CASES:
        want = math.exp(-2 * n * max(alpha - k / n, 0) ** 2)
        assert hoeffding_pvalue(k / n, n, alpha) == pytest.approx(want, rel=1e-12)
    assert hoeffding_pvalue(0.1, 50, 0.2) == pytest.approx(math.exp(-1))  # 2·50·0.1² = 1


def test_hoeffding_bentkus_against_formula_and_hand_values() -> None:
    for k, n, alpha in CASES:
        assert hoeffding_bentkus_pvalue(k / n, n, alpha) == pytest.approx(
            reference_hb(k, n, alpha), rel=1e-10
        )
    # R̂ = 0: Hoeffding gives (1 − α)ⁿ, Bentkus e·(1 − α)ⁿ, so p = (1 − α)ⁿ.
    assert hoeffding_bentkus_pvalue(0.0, 2, 0.5) == pytest.approx(0.25)
    # n = 4, R̂ = 1/4, α = 1/2: Hoeffding's exp(−n h1) = 2¹ · (2/3)³ = 16/27 < e·5/16.
    assert hoeffding_bentkus_pvalue(0.25, 4, 0.5) == pytest.approx(16 / 27)
    # n = 50, R̂ = 0.1, α = 0.2: the Bentkus term e·P(Bin(50, 0.2) ≤ 5) ≈ 0.131 is smaller.
    tail = sum(math.comb(50, j) * 0.2**j * 0.8 ** (50 - j) for j in range(6))
    assert hoeffding_bentkus_pvalue(0.1, 50, 0.2) == pytest.approx(math.e * tail, rel=1e-10)


def test_pvalues_vectorise_and_edge_cases() -> None:
    risks, counts = np.array([k / n for k, n, _ in CASES]), np.array([n for _, n, _ in CASES])
    got = hoeffding_bentkus_pvalue(risks, counts, 0.2)
    assert got.shape == (len(CASES),)
    np.testing.assert_allclose(got, [reference_hb(k, n, 0.2) for k, n, _ in CASES], rtol=1e-10)
    # A floating-point mean 0.1 + 0.2 over 10 images means 3 failures, not 4.
    assert hoeffding_bentkus_pvalue(0.1 + 0.2, 10, 0.5) == pytest.approx(reference_hb(3, 10, 0.5))
    for pvalue in (hoeffding_pvalue, hoeffding_bentkus_pvalue):
        np.testing.assert_array_equal(pvalue([0.5, 0.9, np.nan], [10, 10, 0], 0.5), [1, 1, 1])
        assert pvalue(0.0, 10, 0.2) < pvalue(0.1, 10, 0.2) < pvalue(0.15, 10, 0.2)
        with pytest.raises(ValueError, match="alpha"):
            pvalue(0.1, 10, 1.0)
        with pytest.raises(ValueError, match="risk_hat"):
            pvalue(1.5, 10, 0.5)
        with pytest.raises(ValueError, match="n must be"):
            pvalue(0.1, 2.5, 0.5)


@pytest.mark.parametrize("pvalue", [hoeffding_pvalue, hoeffding_bentkus_pvalue])
def test_pvalues_are_super_uniform_at_the_boundary_null(pvalue) -> None:
    # True risk exactly α: P(p ≤ u) ≤ u must hold, for binary and for continuous losses.
    rng, n, alpha, reps = np.random.default_rng(0), 40, 0.2, 20_000
    binary = rng.binomial(n, alpha, size=reps) / n
    continuous = rng.beta(2, 8, size=(reps, n)).mean(axis=1)  # Beta(2, 8) has mean 0.2
    for risks in (binary, continuous):
        p = pvalue(risks, n, alpha)
        for u in (0.01, 0.05, 0.1, 0.2):
            assert (p <= u).mean() <= u + 3 * math.sqrt(u * (1 - u) / reps)


def synthetic_losses(rng: np.random.Generator, risks: np.ndarray, n: int) -> np.ndarray:
    """(n, L) Bernoulli losses with the given true risks, one shared uniform per image, so the
    losses are monotone along λ as on a real path (and strongly dependent across λ)."""
    return (rng.random((n, 1)) < risks[None, :]).astype(float)


@pytest.mark.parametrize("method", ["bonferroni", "fixed_sequence"])
def test_family_wise_error_is_controlled(method: str) -> None:
    # Risks rise along the path; several λ sit just above α, where a naive R̂ ≤ α pick fails.
    rng, alpha, delta, n, reps = np.random.default_rng(1), 0.2, 0.1, 200, 1000
    risks = np.linspace(0.05, 0.35, 16)
    false_claims = naive_false_claims = certified_best = 0
    for _ in range(reps):
        losses = synthetic_losses(rng, risks, n)
        result = learn_then_test(losses, alpha, delta, method=method)  # type: ignore[arg-type]
        false_claims += bool((risks[result.valid] > alpha).any())
        naive_false_claims += bool((risks[losses.mean(0) <= alpha] > alpha).any())
        certified_best += 0 in result.valid
    slack = 3 * math.sqrt(delta * (1 - delta) / reps)
    assert false_claims / reps <= delta + slack
    assert naive_false_claims / reps > 3 * delta  # the setting does punish a wrong selection
    assert certified_best / reps > 0.9  # and the test has power where the risk is low


def test_bonferroni_and_fixed_sequence_mechanics() -> None:
    # 12 failures out of 100 at α = 0.2: p ≈ 0.04, between δ/3 and δ for δ = 0.1.
    column = np.r_[np.ones(12), np.zeros(88)]
    losses = np.stack([np.zeros(100), column, column], axis=1)
    p = reference_hb(12, 100, 0.2)
    assert 0.1 / 3 < p < 0.1
    assert learn_then_test(losses, 0.2, 0.1).valid.tolist() == [0]
    assert learn_then_test(losses, 0.2, 0.1, order=[1, 2]).valid.tolist() == []  # δ/2 still < p
    assert learn_then_test(losses, 0.2, 0.1, order=[1]).valid.tolist() == [1]
    fixed = learn_then_test(losses, 0.2, 0.1, method="fixed_sequence")
    assert fixed.valid.tolist() == [0, 1, 2]
    np.testing.assert_allclose(fixed.pvalues, [reference_hb(0, 100, 0.2), p, p], rtol=1e-10)
    stops = np.stack([np.zeros(100), np.ones(100), np.zeros(100)], axis=1)
    assert learn_then_test(stops, 0.2, 0.1, method="fixed_sequence").valid.tolist() == [0]
    back = learn_then_test(stops, 0.2, 0.1, method="fixed_sequence", order=[2, 0, 1])
    assert back.valid.tolist() == [2, 0]


def test_defined_risks_against_a_loop() -> None:
    """The risk over the images with a defined loss, column by column, as a plain loop."""
    rng = np.random.default_rng(4)
    losses = rng.random((30, 4, 2))
    losses[rng.random(losses.shape) < 0.3] = np.nan
    losses[:, 2, 1] = np.nan  # no image defined
    risks, counts = defined_risks(losses)
    assert risks.shape == counts.shape == (4, 2) and counts.dtype == np.int64
    for j in range(4):
        for k in range(2):
            kept = [x for x in losses[:, j, k].tolist() if not math.isnan(x)]
            assert counts[j, k] == len(kept)
            if kept:
                assert risks[j, k] == pytest.approx(sum(kept) / len(kept), abs=1e-15)
            else:
                assert math.isnan(risks[j, k])


def test_undefined_losses_are_left_out_and_counted() -> None:
    losses = np.array([[0.0, np.nan, np.nan], [0.5, 1.0, np.nan], [np.nan, 0.0, np.nan]])
    result = learn_then_test(torch.tensor(losses), 0.5, 0.1, bound="hoeffding")
    assert result.n.tolist() == [2, 2, 0] and result.n_undefined.tolist() == [1, 1, 3]
    np.testing.assert_allclose(result.risk, [0.25, 0.5, np.nan])
    np.testing.assert_allclose(result.pvalues, [math.exp(-2 * 2 * 0.25**2), 1.0, 1.0])
    assert result.best([1.0, 2.0, 3.0]) is None  # nothing certified with 2 images


def test_best_picks_among_valid() -> None:
    losses = np.zeros((200, 4))
    losses[:, 3] = 1  # only λ = 3 fails
    result = learn_then_test(losses, 0.1, 0.05)
    assert result.valid.tolist() == [0, 1, 2]
    assert result.best([0.3, 0.9, 0.9, 5.0]) == 1  # tie → first valid; λ = 3 is not valid
    assert result.best([0.3, 0.9, 0.9, 5.0], maximize=False) == 0
    assert result.best([np.nan, np.nan, 0.2, 0.0]) == 2
    with pytest.raises(ValueError, match=r"\(4,\)"):
        result.best([1.0])


def test_learn_then_test_rejects_bad_inputs() -> None:
    with pytest.raises(ValueError, match="n_images, L"):
        learn_then_test(np.zeros(5), 0.1, 0.1)
    with pytest.raises(ValueError, match=r"\[0, 1\]"):
        learn_then_test(np.full((3, 2), 2.0), 0.1, 0.1)
    with pytest.raises(ValueError, match="delta"):
        learn_then_test(np.zeros((3, 2)), 0.1, 1.5)
    with pytest.raises(ValueError, match="method"):
        learn_then_test(np.zeros((3, 2)), 0.1, 0.1, method="holm")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="distinct"):
        learn_then_test(np.zeros((3, 2)), 0.1, 0.1, order=[0, 0])
    with pytest.raises(ValueError, match="distinct"):
        learn_then_test(np.zeros((3, 2)), 0.1, 0.1, order=[2])


def test_per_image_losses_from_hand_counted_cases() -> None:
    tp = torch.tensor([[3, 0, 0], [1, 2, 5]])  # (n_images, L)
    fn = torch.tensor([[1, 2, 0], [0, 2, 0]])
    fp = torch.tensor([[0, 4, 0], [1, 0, 5]])
    want = {
        "recall": (tp + fn, [[1 / 4, 1.0, math.nan], [0.0, 0.5, 0.0]]),
        "precision": (tp + fp, [[0.0, 1.0, math.nan], [0.5, 0.0, 0.5]]),
    }
    for metric, (whole, losses) in want.items():
        got = per_image_loss(torch.stack([tp, whole], -1), metric)
        assert got.dtype == torch.float64
        torch.testing.assert_close(got, torch.tensor(losses).double(), equal_nan=True)
    n_gt, n_pred = torch.tensor([[4, 0], [2, 1]]), torch.tensor([[3, 0], [0, 2]])
    torch.testing.assert_close(
        per_image_loss(torch.stack([torch.tensor([[1, 0], [2, 0]]), n_gt], -1), "fn_rate"),
        torch.tensor([[0.25, math.nan], [1.0, 0.0]]).double(),
        equal_nan=True,
    )
    torch.testing.assert_close(
        per_image_loss(torch.stack([torch.tensor([[3, 0], [0, 1]]), n_pred], -1), "fp_rate"),
        torch.tensor([[1.0, math.nan], [math.nan, 0.5]]).double(),
        equal_nan=True,
    )
    with pytest.raises(ValueError, match="numerator <= denominator"):
        per_image_loss(torch.tensor([[[3, 2]]]), "fp_rate")
