"""Certifying a designed value system against several constraints at once: Pareto Testing
(docs/definitions.md §20).

Laufer-Goldshtein, Fisch, Barzilay, Jaakkola (2023), "Efficiently controlling multiple risks with
Pareto Testing" (ICLR). The calibration images are split into D1 and D2. On D1 the candidates'
empirical risks ``R̂_1 … R̂_K`` (and an objective) give a Pareto front, ordered by the largest of
each candidate's K Hoeffding–Bentkus p-values on D1, smallest first. On D2 each candidate in that
order gets ``p = max_i p_i`` (the p-value of "some constraint is violated": each ``H_i: R_i > α_i``
has a valid p-value, so their maximum is one for their union), and fixed-sequence testing rejects
while ``p ≤ δ``, stopping at the first that is not. Since the order depends on D1 only, every
certified candidate meets every constraint with probability at least 1 − δ over the draw of D2.

Images on which a loss is undefined (NaN) are left out of that constraint's risk and test, and
counted (``n_d1``, ``n_d2``), as in Learn-then-Test (:mod:`.guarantee`).

Pure numpy / scipy; nothing here knows of models, matrices or Lightning.
"""

from __future__ import annotations

import hashlib
import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from costseg.calibration.guarantee import defined_risks, hoeffding_bentkus_pvalue

SCAN_LIMIT = 10**7
"""The largest size :func:`images_needed` scans for the smallest one; beyond it, the size at
which the Hoeffding part alone allows the risk."""


def split_images(n: int, seed: int = 0) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """D1 and D2: a seeded random ⌊n / 2⌋ of the n calibration images and the others, each as
    ascending positions.

    Image i's place in the draw is the BLAKE2b hash of ``(seed, i)``: the same split on every
    machine and version, a different one for another seed. A random split, not halves in order:
    datasets such as Cityscapes list their images city by city, and halves in order would not be
    exchangeable.

    >>> d1, d2 = split_images(6, seed=0)
    >>> len(d1), len(d2), sorted([*d1, *d2]) == list(range(6))
    (3, 3, True)
    """
    if n < 0:
        raise ValueError(f"need n >= 0 images, got {n}")
    keys = [hashlib.blake2b(f"{seed}:{i}".encode(), digest_size=8).digest() for i in range(n)]
    order = sorted(range(n), key=lambda i: keys[i])
    half = n // 2
    d1, d2 = sorted(order[:half]), sorted(order[half:])
    return np.array(d1, dtype=np.int64), np.array(d2, dtype=np.int64)


def pareto_front(objectives: ArrayLike) -> NDArray[np.int64]:
    """The indices of the non-dominated points, all objectives minimised.

    Point j dominates point i when ``o_j ≤ o_i`` in every objective and ``o_j < o_i`` in one.
    Points that tie in every objective do not dominate each other, so duplicates on the front
    are all kept; NaN counts as +inf (the worst value).

    Args:
        objectives: (L, M) values to minimise.

    Returns:
        int64 indices of the front, ascending.

    >>> pareto_front([[1, 3], [2, 2], [2, 3], [3, 1], [1, 3]]).tolist()
    [0, 1, 3, 4]
    """
    values = np.asarray(objectives, dtype=np.float64)
    if values.ndim != 2:
        raise ValueError(f"objectives must be (L, M); got shape {values.shape}")
    values = np.where(np.isnan(values), np.inf, values)
    size = len(values)
    block = max(1, 2**22 // max(size * values.shape[1], 1))
    dominated = np.zeros(size, dtype=bool)
    for start in range(0, size, block):
        rows = values[start : start + block, None, :]  # (b, 1, M) against (L, M)
        no_worse = (values[None] <= rows).all(axis=2)
        better = (values[None] < rows).any(axis=2)
        dominated[start : start + block] = (no_worse & better).any(axis=1)
    return np.flatnonzero(~dominated).astype(np.int64)


@dataclass(frozen=True)
class ParetoTestingResult:
    """The outcome of :func:`pareto_testing` for L candidates and K constraints.

    Attributes:
        front: int64 indices of the candidates on D1's Pareto front, ascending.
        order: ``front`` in testing order (largest D1 p-value ascending).
        pvalues_d1, pvalues_d2: (L, K) Hoeffding–Bentkus p-values of ``H_i: R_i > α_i`` on D1
            and on D2 (1 where no image has a defined loss). Only ``certified`` carries the
            guarantee; the other D2 p-values are shown, not tested.
        risks_d1, risks_d2: (L, K) empirical risks over the images with a defined loss (NaN if
            none).
        n_d1, n_d2: (L, K) int64 images with a defined loss behind each risk (of n1, n2).
        certified: int64 indices rejected by the fixed-sequence test on D2, in testing order.
        alphas: (K,) levels α_i. delta: δ.
        best: when nothing is certified, the front's candidate closest to meeting every
            constraint on D1 (the smallest largest excess ``R̂_i − α_i``; the first in ``order``
            of ties), else None.
        failed: its constraint with the largest D2 p-value (of ties, the first with a defined
            D2 risk, else the first), else None.
        needed_n: the images with a defined loss at which its observed risk on ``failed`` would
            pass at δ (:func:`images_needed`); None when certified, or the risk is ≥ α.
        needed_images: ``needed_n`` as D2 images, at D2's share of images with a defined loss
            (D1's where no D2 image has one).
    """

    front: NDArray[np.int64]
    order: NDArray[np.int64]
    pvalues_d1: NDArray[np.float64]
    pvalues_d2: NDArray[np.float64]
    risks_d1: NDArray[np.float64]
    risks_d2: NDArray[np.float64]
    n_d1: NDArray[np.int64]
    n_d2: NDArray[np.int64]
    certified: NDArray[np.int64]
    alphas: NDArray[np.float64]
    delta: float
    best: int | None = None
    failed: int | None = None
    needed_n: int | None = None
    needed_images: int | None = None


def pareto_testing(
    losses_d1: ArrayLike,
    losses_d2: ArrayLike,
    alphas: ArrayLike,
    delta: float,
    objective_d1: ArrayLike | None = None,
    maximize: bool = True,
) -> ParetoTestingResult:
    """Pareto Testing (docs/definitions.md §20): the candidates certified to meet every
    constraint ``R_i ≤ α_i``, jointly with probability ≥ 1 − δ over the draw of D2.

    1. On D1: the Pareto front of ``(R̂_1 … R̂_K, objective)`` (``−objective`` when
       ``maximize``; without an objective, of the risks alone).
    2. Order the front by ``max_i p_i`` on D1, smallest first; ties go to the better D1
       objective, then to the lower index.
    3. On D2, along that order: ``p = max_i p_i`` on D2; reject while ``p ≤ δ``, stop at the
       first candidate that is not rejected.

    Args:
        losses_d1: (n1, L, K) per-image losses in [0, 1] of L candidates and K constraints on
            D1; NaN where undefined.
        losses_d2: (n2, L, K) the same on D2 (disjoint images).
        alphas: (K,) levels α_i in (0, 1).
        delta: δ in (0, 1).
        objective_d1: (L,) objective on D1 (NaN: worst), or None.
        maximize: whether a larger objective is better.

    Returns:
        :class:`ParetoTestingResult`.

    >>> rng = np.random.default_rng(0)
    >>> risks = np.array([[0.02, 0.3], [0.05, 0.05], [0.3, 0.02]])   # 3 candidates, 2 constraints
    >>> d1 = (rng.random((300, 3, 2)) < risks).astype(float)
    >>> d2 = (rng.random((300, 3, 2)) < risks).astype(float)
    >>> result = pareto_testing(d1, d2, alphas=[0.1, 0.1], delta=0.1)
    >>> result.front.tolist(), result.certified.tolist()
    ([0, 1, 2], [1])
    """
    d1, d2, levels = _check(losses_d1, losses_d2, alphas, delta)
    count = d1.shape[1]
    risks_d1, n_d1, p_d1 = _tests(d1, levels)
    risks_d2, n_d2, p_d2 = _tests(d2, levels)
    sign = -1.0 if maximize else 1.0
    if objective_d1 is None:
        signed = np.zeros(count)
        front = pareto_front(risks_d1)
    else:
        signed = sign * np.asarray(objective_d1, dtype=np.float64)
        if signed.shape != (count,):
            raise ValueError(f"objective_d1 must be ({count},); got shape {signed.shape}")
        signed = np.where(np.isnan(signed), np.inf, signed)
        front = pareto_front(np.column_stack([risks_d1, signed]))
    order = front[np.lexsort((front, signed[front], p_d1[front].max(axis=1)))]
    failed_at = np.flatnonzero(p_d2[order].max(axis=1) > delta)
    certified = order[: failed_at[0] if len(failed_at) else len(order)]
    result = ParetoTestingResult(
        front, order, p_d1, p_d2, risks_d1, risks_d2, n_d1, n_d2,
        certified.astype(np.int64), levels, float(delta),
    )  # fmt: skip
    if len(certified):
        return result
    excess = np.nan_to_num(risks_d1[order] - levels, nan=np.inf).max(axis=1)
    best = int(order[np.argmin(excess)])  # the first of ties
    worst = np.flatnonzero(p_d2[best] == p_d2[best].max())
    defined = worst[n_d2[best, worst] > 0]  # of ties, one whose risk is measured, if any
    failed = int(defined[0] if len(defined) else worst[0])
    observed = risks_d2[best, failed] if n_d2[best, failed] else risks_d1[best, failed]
    needed = None
    if np.isfinite(observed) and observed < levels[failed]:
        needed = images_needed(float(observed), float(levels[failed]), float(delta))
    # images per defined one: D2's share, or D1's where no D2 image defines the loss
    share = n_d2[best, failed] / len(d2) if len(d2) else 0.0
    if share == 0 and len(d1):
        share = n_d1[best, failed] / len(d1)
    images = math.ceil(needed / share) if needed is not None and share > 0 else None
    return ParetoTestingResult(
        **{**result.__dict__, "best": best, "failed": failed, "needed_n": needed,
           "needed_images": images}
    )  # fmt: skip


def choose(
    result: ParetoTestingResult, objective_all: ArrayLike, maximize: bool = True
) -> int | None:
    """Among the certified candidates, the one with the best finite objective (measured on all
    calibration images); ties go to the one tested first. None when none is certified.

    >>> result = pareto_testing(np.zeros((60, 3, 1)), np.zeros((60, 3, 1)), [0.1], 0.1)
    >>> result.certified.tolist(), choose(result, [0.2, 0.7, 0.7])
    ([0, 1, 2], 1)
    """
    values = np.asarray(objective_all, dtype=np.float64)
    if values.shape != result.pvalues_d1.shape[:1]:
        raise ValueError(f"objective_all must be ({len(result.pvalues_d1)},); got {values.shape}")
    finite = [int(i) for i in result.certified if np.isfinite(values[i])]
    if not finite:
        return None
    sign = 1.0 if maximize else -1.0
    return max(finite, key=lambda i: sign * values[i])  # max keeps the first of ties


def images_needed(risk: float, alpha: float, delta: float, limit: int = SCAN_LIMIT) -> int | None:
    """The smallest n at which the Hoeffding–Bentkus p-value of ``H: R > α`` at the empirical
    risk ``risk`` is ≤ δ (the risk held fixed as n grows); None when ``risk ≥ α``.

    The p-value is not monotone in n (its binomial part rounds ``n·R̂`` up), so n is found by a
    scan up to the size at which the Hoeffding part alone passes, ``⌈log(1/δ) / h₁(R̂, α)⌉``;
    when that exceeds ``limit``, it is returned instead (an upper bound on the smallest n).

    >>> images_needed(0.0, 0.05, 0.1)              # (1 − α)ⁿ ≤ δ: n = 45
    45
    >>> images_needed(0.1, 0.05, 0.1) is None
    True
    """
    if not (0 <= risk <= 1 and 0 < alpha < 1 and 0 < delta < 1):
        raise ValueError(f"need risk in [0, 1], alpha and delta in (0, 1); got {risk}, {alpha}, "
                         f"{delta}")  # fmt: skip
    if risk >= alpha:
        return None
    h1 = (risk * math.log(risk / alpha) if risk > 0 else 0.0) + (1 - risk) * math.log(
        (1 - risk) / (1 - alpha)
    )
    hoeffding = math.ceil(math.log(1 / delta) / h1) + 1  # + 1: rounding in exp(−n h₁)
    if hoeffding > limit:
        return hoeffding
    chunk = 1 << 14
    for start in range(1, hoeffding + 1, chunk):
        sizes = np.arange(start, min(start + chunk, hoeffding + 1))
        passing = np.flatnonzero(hoeffding_bentkus_pvalue(risk, sizes, alpha) <= delta)
        if len(passing):
            return int(sizes[passing[0]])
    return hoeffding


def _tests(
    losses: NDArray[np.float64], alphas: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.int64], NDArray[np.float64]]:
    """(n, L, K) losses → the (L, K) risks over defined images, their counts, HB p-values."""
    risks, count = defined_risks(losses)  # no defined image: NaN risk, p = 1
    pvalues = np.column_stack(
        [hoeffding_bentkus_pvalue(risks[:, k], count[:, k], alphas[k]) for k in range(len(alphas))]
    ).reshape(risks.shape)
    return risks, count, pvalues


def _check(
    losses_d1: ArrayLike, losses_d2: ArrayLike, alphas: ArrayLike, delta: float
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    d1, d2 = np.asarray(losses_d1, np.float64), np.asarray(losses_d2, np.float64)
    levels = np.asarray(alphas, np.float64).reshape(-1)
    if d1.ndim != 3 or d2.ndim != 3 or d1.shape[1:] != d2.shape[1:] or d1.shape[1] == 0:
        raise ValueError(
            f"losses must be (n1, L, K) and (n2, L, K) with L >= 1; got {d1.shape}, {d2.shape}"
        )
    if d1.shape[2] != len(levels) or len(levels) == 0:
        raise ValueError(f"alphas must give one level per constraint ({d1.shape[2]}); got "
                         f"{levels.tolist()}")  # fmt: skip
    for values in (d1, d2):
        if np.any((values < 0) | (values > 1)) or np.any(np.isinf(values)):
            raise ValueError("losses must lie in [0, 1] (NaN = undefined)")
    if not np.all((levels > 0) & (levels < 1)):
        raise ValueError(f"alphas must lie in (0, 1); got {levels.tolist()}")
    if not 0 < delta < 1:
        raise ValueError(f"delta must lie in (0, 1); got {delta}")
    return d1, d2, levels
