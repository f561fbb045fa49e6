"""Choosing a value system with a guarantee: Learn-then-Test (docs/definitions.md §7).

Angelopoulos, Bates, Candès, Jordan, Lei (2021), "Learn then Test: Calibrating Predictive
Algorithms to Achieve Risk Control". For each candidate λ (a grid point or an α of the Bayes↔ML
path) and each calibration image i there is a loss ``L_i(λ) ∈ [0, 1]`` (NaN where undefined);
each null hypothesis ``H_λ: R(λ) > α`` gets a p-value from the empirical risk, and a
family-wise error control (Bonferroni or fixed-sequence testing) keeps ``P(some rejected H_λ is
true) ≤ δ``. Every rejected λ then has ``R(λ) ≤ α`` with probability at least 1 − δ over the
draw of calibration images. Images on which a λ's loss is undefined are left out of that λ's
test (so its risk is the risk over images where the loss is defined) and counted.

Pure numpy / scipy / torch; nothing here knows of models or Lightning.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray
from torch import Tensor

Method = Literal["bonferroni", "fixed_sequence"]
Bound = Literal["hoeffding", "hoeffding_bentkus"]


def defined_risks(losses: ArrayLike) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
    """The risk over the images with a defined loss: the mean of per-image ``losses`` (images
    along the first axis, NaN where a loss is undefined) over the images where each is defined,
    and how many those are; NaN where none is.

    >>> risk, count = defined_risks(np.array([[0.5, np.nan, 1.0], [0.0, np.nan, np.nan]]))
    >>> risk.tolist(), count.tolist()
    ([0.25, nan, 1.0], [2, 0, 1])
    """
    values = np.asarray(losses, dtype=np.float64)
    defined = ~np.isnan(values)
    count = defined.sum(axis=0)
    total = np.where(defined, values, 0.0).sum(axis=0)
    return np.where(count > 0, total / np.maximum(count, 1), np.nan), count.astype(np.int64)


def _pvalue_inputs(
    risk_hat: ArrayLike, n: ArrayLike, alpha: float
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Broadcast float64 risks and counts; validate the ranges."""
    risk, count = np.broadcast_arrays(np.asarray(risk_hat, float), np.asarray(n, float))
    if not 0 < alpha < 1:
        raise ValueError(f"alpha must lie in (0, 1); got {alpha}")
    if np.any(count < 0) or np.any(count != np.round(count)):
        raise ValueError(f"n must be non-negative integers; got {np.asarray(n)}")
    defined = count > 0
    if np.any(np.isnan(risk) & defined) or np.any((risk[defined] < 0) | (risk[defined] > 1)):
        raise ValueError(f"risk_hat must lie in [0, 1] where n > 0; got {np.asarray(risk_hat)}")
    return risk, count


def hoeffding_pvalue(risk_hat: ArrayLike, n: ArrayLike, alpha: float) -> NDArray[np.float64]:
    """Hoeffding p-value ``exp(−2 n (α − R̂)₊²)`` of ``H: R > α`` (vectorised over λ).

    Args:
        risk_hat: Empirical risks R̂ in [0, 1], any shape.
        n: Number of images behind each R̂ (broadcast against ``risk_hat``); n = 0 gives p = 1.
        alpha: Risk level α in (0, 1).

    Returns:
        float64 p-values, the broadcast shape.

    >>> hoeffding_pvalue([0.0, 0.1, 0.3], 50, 0.2).round(6).tolist()    # exp(-4), exp(-1), 1
    [0.018316, 0.367879, 1.0]
    """
    risk, count = _pvalue_inputs(risk_hat, n, alpha)
    gap = np.clip(alpha - np.nan_to_num(risk, nan=1.0), 0, None)
    return np.where(count > 0, np.exp(-2 * count * gap**2), 1.0)


def hoeffding_bentkus_pvalue(
    risk_hat: ArrayLike, n: ArrayLike, alpha: float
) -> NDArray[np.float64]:
    """Hoeffding–Bentkus p-value of ``H: R > α`` (LTT, Proposition 3; vectorised over λ).

    ``p = min(exp(−n h₁(R̂ ∧ α, α)), e · P(Binomial(n, α) ≤ ⌈n R̂⌉))`` with
    ``h₁(a, b) = a log(a / b) + (1 − a) log((1 − a) / (1 − b))``. Valid for any loss in [0, 1].
    ``n R̂`` is rounded to 9 decimals before the ceiling, so that floating-point error in a mean
    of binary losses (e.g. 0.1 + 0.2) does not raise it to the next integer.

    Args:
        risk_hat: Empirical risks R̂ in [0, 1], any shape.
        n: Number of images behind each R̂ (broadcast against ``risk_hat``); n = 0 gives p = 1.
        alpha: Risk level α in (0, 1).

    Returns:
        float64 p-values, the broadcast shape.

    >>> p = hoeffding_bentkus_pvalue([0.0, 0.1, 0.3], 50, 0.2)
    >>> p.round(6).tolist()          # R̂ = 0: Hoeffding's 0.8⁵⁰; R̂ = 0.1: e·P(Bin(50, 0.2) ≤ 5)
    [1.4e-05, 0.130552, 1.0]
    """
    from scipy.special import xlogy  # scipy.stats takes ~0.5 s to import: only when needed
    from scipy.stats import binom

    risk, count = _pvalue_inputs(risk_hat, n, alpha)
    defined = count > 0
    r = np.where(defined, risk, 0.0)
    a = np.minimum(r, alpha)
    h1 = xlogy(a, a / alpha) + xlogy(1 - a, (1 - a) / (1 - alpha))
    hoeffding = np.exp(-count * h1)
    bentkus = np.e * binom.cdf(np.ceil(np.round(count * r, 9)), count, alpha)
    return np.where(defined, np.minimum(np.minimum(hoeffding, bentkus), 1.0), 1.0)


@dataclass(frozen=True)
class LTTResult:
    """The outcome of :func:`learn_then_test` for L candidates λ.

    Attributes:
        valid: int64 indices of the λ whose null ``R(λ) > α`` was rejected: ascending for
            Bonferroni, in testing order for fixed-sequence.
        pvalues: (L,) float64 p-values (1 where no image has a defined loss).
        risk: (L,) float64 empirical risk over the images with a defined loss (NaN if none).
        n: (L,) int64 images with a defined loss, used in each test.
        n_undefined: (L,) int64 images left out (NaN loss).
        alpha, delta, method, bound: The settings.
    """

    valid: NDArray[np.int64]
    pvalues: NDArray[np.float64]
    risk: NDArray[np.float64]
    n: NDArray[np.int64]
    n_undefined: NDArray[np.int64]
    alpha: float
    delta: float
    method: Method
    bound: Bound

    def best(
        self, objective: ArrayLike, maximize: bool = True, prefer: ArrayLike | None = None
    ) -> int | None:
        """Among the valid λ, the index with the best finite ``objective`` (L,) value.

        Ties go to the λ of largest ``prefer`` (L,) (e.g. the defer cost), then to the one
        listed first in ``valid``; None when no valid λ has a finite value.

        >>> result = learn_then_test(np.zeros((60, 3)), alpha=0.1, delta=0.1)
        >>> result.best([0.5, 0.9, 0.9]), result.best([0.5, 0.9, 0.9], prefer=[0, 1, 2])
        (1, 2)
        """
        values = np.asarray(objective, float)
        ranks = np.zeros_like(values) if prefer is None else np.asarray(prefer, float)
        if values.shape != self.pvalues.shape or ranks.shape != values.shape:
            raise ValueError(f"objective and prefer must be ({len(self.pvalues)},)")
        candidates = [int(i) for i in self.valid if np.isfinite(values[i])]
        if not candidates:
            return None
        sign = 1.0 if maximize else -1.0
        return max(candidates, key=lambda i: (sign * values[i], ranks[i]))  # first of ties


def learn_then_test(
    losses: ArrayLike | Tensor,
    alpha: float,
    delta: float,
    method: Method = "bonferroni",
    order: Sequence[int] | None = None,
    bound: Bound = "hoeffding_bentkus",
) -> LTTResult:
    """Learn-then-Test: the λ certified to have risk ≤ α, with probability ≥ 1 − δ.

    Args:
        losses: (n_images, L) per-image losses in [0, 1]; NaN where undefined.
        alpha: Risk level α in (0, 1).
        delta: Family-wise error level δ in (0, 1).
        method: ``"bonferroni"``: reject ``H_λ`` when ``p_λ ≤ δ / |family|``;
            ``"fixed_sequence"``: test along ``order`` at level δ and stop at the first λ not
            rejected (the order must be fixed before seeing the calibration losses).
        order: Distinct λ indices: the testing path (fixed-sequence) or the family tested
            (Bonferroni); None means all λ in index order.
        bound: ``"hoeffding_bentkus"`` (default) or ``"hoeffding"`` p-values.

    Returns:
        :class:`LTTResult`.

    >>> losses = np.zeros((100, 3))
    >>> losses[:30, 1], losses[:, 2] = 1, 1           # true risks about 0, 0.3, 1
    >>> learn_then_test(losses, alpha=0.5, delta=0.1).valid.tolist()
    [0, 1]
    >>> learn_then_test(losses, alpha=0.5, delta=0.1, method="fixed_sequence",
    ...                 order=[2, 1, 0]).valid
    array([], dtype=int64)
    """
    values = _check_losses(losses, delta, method, bound)
    risk, count = defined_risks(values)  # a column without a defined loss: NaN risk, p = 1
    pvalue = hoeffding_bentkus_pvalue if bound == "hoeffding_bentkus" else hoeffding_pvalue
    pvalues = pvalue(risk, count, alpha)
    path = _path(order, values.shape[1])
    if method == "bonferroni":
        valid = np.sort(path[pvalues[path] <= delta / max(len(path), 1)])
    else:
        failed = np.flatnonzero(pvalues[path] > delta)
        valid = path[: failed[0] if len(failed) else len(path)]
    return LTTResult(
        valid.astype(np.int64), pvalues, risk, count, len(values) - count, alpha, delta, method,
        bound,
    )  # fmt: skip


def fixed_sequences(
    losses: ArrayLike | Tensor,
    alpha: float,
    delta: float,
    paths: Sequence[Sequence[int]],
    bound: Bound = "hoeffding_bentkus",
) -> LTTResult:
    """Fixed-sequence testing along each of several disjoint paths at δ / len(paths)
    (Bonferroni over the paths), e.g. one path per rule from its safest candidate up.

    With one path this is :func:`learn_then_test` with ``method="fixed_sequence"``. ``valid``
    lists each path's rejected λ in testing order, path after path.

    >>> losses = np.zeros((100, 4))
    >>> losses[:40, 1] = 1                             # risks about 0, 0.4, 0, 0
    >>> fixed_sequences(losses, alpha=0.2, delta=0.1, paths=[[0, 1], [2, 3]]).valid.tolist()
    [0, 2, 3]
    """
    flat = [int(i) for path in paths for i in path]
    if not paths or len(set(flat)) != len(flat):
        raise ValueError(f"paths must be one or more disjoint index lists; got {list(paths)}")
    level = delta / len(paths)
    tests = [learn_then_test(losses, alpha, level, "fixed_sequence", p, bound) for p in paths]
    valid = np.concatenate([t.valid for t in tests]).astype(np.int64)
    return replace(tests[0], valid=valid, delta=delta)


def learn_then_test_paths(
    losses: ArrayLike | Tensor,
    alpha: float,
    delta: float,
    method: Method,
    paths: Sequence[Sequence[int]] = (),
    bound: Bound = "hoeffding_bentkus",
) -> LTTResult:
    """:func:`learn_then_test` over every candidate, fixed-sequence along each of ``paths``
    (:func:`fixed_sequences`) where the candidates come in paths, else in index order.

    >>> losses = np.zeros((100, 4))
    >>> losses[:40, 1] = 1
    >>> learn_then_test_paths(losses, 0.2, 0.1, "fixed_sequence", [[0, 1], [2, 3]]).valid.tolist()
    [0, 2, 3]
    """
    if method == "fixed_sequence" and paths:
        return fixed_sequences(losses, alpha, delta, paths, bound)
    return learn_then_test(losses, alpha, delta, method, bound=bound)


def minimum_images(
    alpha: float, delta: float, tests: int = 1, bound: Bound = "hoeffding_bentkus"
) -> int:
    """Fewest calibration images with which even a zero empirical risk is certified at level
    α when ``tests`` tests share δ: Hoeffding–Bentkus' p-value at risk 0 is (1 − α)ⁿ,
    Hoeffding's exp(−2 n α²).

    >>> minimum_images(0.05, 0.1), minimum_images(0.05, 0.1, bound="hoeffding")
    (45, 461)
    """
    level = delta / tests
    if bound == "hoeffding":
        return math.ceil(-math.log(level) / (2 * alpha**2))
    return math.ceil(math.log(level) / math.log1p(-alpha))


def tests_sharing_delta(method: Method, candidates: int, paths: int = 0) -> int:
    """How many tests share δ: every candidate (Bonferroni), or each fixed-sequence path (one
    when the candidates are one path).

    >>> tests_sharing_delta("bonferroni", 63, 3), tests_sharing_delta("fixed_sequence", 63, 3)
    (63, 3)
    """
    return candidates if method == "bonferroni" else max(1, paths)


def _check_losses(losses: ArrayLike | Tensor, delta: float, method: str, bound: str) -> NDArray:
    """(n_images, L) float64 losses, after checking them and the settings."""
    values = np.asarray(losses.detach().cpu() if isinstance(losses, Tensor) else losses, float)
    if values.ndim != 2:
        raise ValueError(f"losses must be (n_images, L); got shape {values.shape}")
    if np.any((values < 0) | (values > 1)) or np.any(np.isinf(values)):
        raise ValueError("losses must lie in [0, 1] (NaN = undefined)")
    if not 0 < delta < 1:
        raise ValueError(f"delta must lie in (0, 1); got {delta}")
    if method not in ("bonferroni", "fixed_sequence"):
        raise ValueError(f"method must be 'bonferroni' or 'fixed_sequence'; got {method!r}")
    if bound not in ("hoeffding", "hoeffding_bentkus"):
        raise ValueError(f"bound must be 'hoeffding' or 'hoeffding_bentkus'; got {bound!r}")
    return values


def _path(order: Sequence[int] | None, size: int) -> NDArray[np.int64]:
    if order is None:
        return np.arange(size)
    path = np.asarray(order, dtype=np.int64).reshape(-1)
    if len(set(path.tolist())) != len(path) or np.any((path < 0) | (path >= size)):
        raise ValueError(f"order must hold distinct indices in [0, {size}); got {list(order)}")
    return path
