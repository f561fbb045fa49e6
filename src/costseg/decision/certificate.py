"""Every rounding bound of the decision layer's certificates (docs/definitions.md §1).

A fast path sums nonnegative terms, so each computed cost errs by at most ``γ`` times its own
value; the reference errs by at most ``eps · T`` (``T``: a bound on the magnitude of its costs).
A gap between the best two costs wider than both certifies the reference's decision. The fast
paths (:mod:`costseg.decision.tensor_ops`, ``cpu/``, ``gpu/``) take their bounds from here.
"""

from __future__ import annotations

import math

import numpy as np
import torch

U32, U64 = 2.0**-24, 2.0**-53  # unit roundoffs of float32 and float64
TINY = 2.0**-120  # absolute slack: covers float32 underflow (below N · 2**-149 per cost)
FLOOR32 = 2.0**-60  # float32 runner-ups below it are never certified: underflow negligible
FLOOR64 = 2.0**-900  # the same for float64 sums
INT_MAX, INF_BITS = 0x7FFFFFFF, 0x7F800000  # INF_BITS: float32 +inf (NaN's patterns lie above)
TEST_MARGIN = 1.25  # a float64 certificate's own rounding: 1.25 on the bound ...
GAP_SHRINK = 1 - 4 * U64  # ... and the gap taken 4 ulps smaller
ROUNDING = 1 + 2.0**-20  # float64 coefficients rounded up past their casts to float32
ONE_PERCENT = 1.01  # on relative slacks: the rounding of the tests that use them
# Inputs of float32 matmuls, per torch.get_float32_matmul_precision (TF32, bfloat16 passes).
MATMUL_INPUT_ROUNDING = {"highest": 0.0, "high": 2.0**-11, "medium": 2.0**-8}


def gamma(m, u: float = U32):
    """``γ_m = m u / (1 - m u)``: the relative error of m roundings (floats or tensors)."""
    return m * u / (1 - m * u)


def reference_eps(n: int, mixtures: bool) -> float:
    """The reference's rounding per T on N classes: N + 4 roundings (a mixed matrix: 4 more,
    those of ``mix_costs``)."""
    return (n + (8 if mixtures else 4)) * U64


def costs_gamma(rho: float, u_in: float, n: int) -> float:
    """float32 costs ``W @ q`` (:class:`~costseg.decision.certified.CertifiedCosts`): ρ of the
    matrix, two roundings of the matmul's inputs, three of q (casts, pixel-wise priors), a dot
    product of length N."""
    return (1 + rho) * (1 + u_in) ** 2 * (1 + U32) ** 3 * (1 + gamma(n)) - 1


def costs_gamma64(n: int) -> float:
    """float64 costs: one rounding of the matrix (minus C.min), one of q, the dot product."""
    return (1 + U64) ** 3 * (1 + gamma(n, U64)) - 1


def more_terms(g: float, count: int, u: float = U64) -> float:
    """γ of sums of ``count`` terms of γ ``g`` each (vertex costs mixed by weights >= 0)."""
    return (1 + g) * (1 + gamma(count, u)) - 1


def top_delta(g: float) -> float:
    """Relative gap that certifies float32 costs of γ ``g``: 2γ for both roundings, γ/2 left for
    the reference's."""
    return 2.5 * g / (1 - g)


def top_floor(g: float, eps: float) -> float:
    """Coefficient of T that the runner-up must reach (the reference's ``eps T`` within γ/2)."""
    return 10 * eps / g


def mixed_gamma(g: float, u_in: float, v: int) -> float:
    """Mixed float32 costs: the vertices' γ, w rounded to float32, the matmul's inputs, a dot
    product of length V."""
    return (1 + g) * (1 + U32) * (1 + u_in) ** 2 * (1 + gamma(v)) - 1


def signs_slack(g: float, u_in: float, v: int, eps: float) -> tuple[float, float]:
    """Slack of mixed signed differences (``Mixer.signs``): relative to ``x_i + x_j`` (the costs'
    γ, V + 4 roundings and the inputs), and per T (the reference's)."""
    g = g / (1 - g)
    h = (1 + U32) ** (v + 4) * (1 + u_in) ** 2 - 1
    return TEST_MARGIN * (g + 2 * h), 2.5 * eps * (1 + g)


def candidates_slack(g: float) -> float:
    """Relative slack of "beaten in every vertex": twice the costs' rounding, and the test's."""
    return 2 * g / (1 - g) * ONE_PERCENT


def certified64(lo, hi, total, g: float, eps: float):
    """float64 certificate of best ``lo`` over runner-up ``hi``: ``hi - lo - g (lo + hi)`` (a lower
    bound on the exact gap, ``g = γ / (1 - γ)``) exceeds the reference's ``2 eps T (1 + g)``."""
    need = TEST_MARGIN * (g * (lo + hi) + 2 * eps * (1 + g) * total) + FLOOR64
    return (hi - lo) * GAP_SHRINK > need


def kernel_gamma(rho: float, n: int, v: int, u: float) -> float:
    """The Triton kernel's sums (:mod:`costseg.decision.gpu.triton_kernel`): N terms per vertex
    cost then V per mixture in the compute type (unit roundoff u), the weights' float64
    construction (4 U64) and their rounding to it (ρ), one rounding of q and of the weights."""
    return (1 + rho + 4 * U64) * (1 + u) ** 2 * (1 + gamma(n + v, u)) - 1


def block_depth_gamma(g: float, n: int) -> float:
    """``g`` with its dot product of length N (any order) replaced by the depth of
    ``block_products``: four terms per pass, at most 2 + ceil(N / 4) roundings per term."""
    shorter = (1 + gamma(2 + -(-n // 4))) / (1 + gamma(n))
    return (1 + g) * shorter - 1


def sparse_gamma(passes: torch.Tensor) -> torch.Tensor:
    """The sparse kernel's row sums: terms rounded at most ``passes + 3`` times, q three times."""
    return (1 + U32) ** 3 * (1 + gamma(passes.double() + 3)) - 1


def sparse_lower_g(g: torch.Tensor) -> torch.Tensor:
    """How far the sparse kernel moves its entries down, per row: past its rounding (and 8 U64 of
    the float64 steps before), 1 % more."""
    margin = g * (1 + U32) * (1 + 8 * U64)
    return ONE_PERCENT * margin / (1 - margin)


def sparse_distance(g: torch.Tensor, row_gamma: torch.Tensor) -> torch.Tensor:
    """``d``: a row's lower bound lies within ``d M`` of its cost (M: the row's magnitude)."""
    return g + U32 * (1 + g) * (1 + 8 * U64) + row_gamma * (1 + g) * (1 + U32)


def sparse_total_up(passes: torch.Tensor) -> torch.Tensor:
    """Factor of the computed ``Σ_k q_k`` up to a bound of it, with the test's roundings."""
    shrink = (1 - U32) ** 3 * (1 - gamma(passes.double() + 3))
    return (1 + U32) ** 3 / shrink * ROUNDING


def round_down32(values: torch.Tensor) -> torch.Tensor:
    """float64 → float32 (as float64), each rounded down."""
    single = values.float()
    above = single.double() > values
    return torch.where(above, torch.nextafter(single, torch.tensor(-math.inf)), single).double()


def round_up32(values: np.ndarray) -> np.ndarray:
    """float64 → the float32 values at or above them (as float64)."""
    single = values.astype(np.float32)
    return np.where(single < values, np.nextafter(single, np.float32(np.inf)), single).astype(float)


def mixture_kernel_params(g: float, g64: float, mix_g: float, eps: float, n: int, v: int):
    """The compiled mixture kernel's bounds (:func:`~.cpu.mixture_kernel.decide_chunk`) from the
    vertex costs' γ (float32 ``g``, float64 ``g64``) and the mixed costs' (``mix_g``): float64
    [vertex Δ, vertex floor, the candidates' three coefficients (float32, rounded up: x_a's, T's
    and the constant's), mixture Δ, mixture floor, the float64 re-check's g and eps]."""
    gamma64 = more_terms(g64, v)  # V more terms >= 0
    gamma, mix_gamma = block_depth_gamma(g, n), block_depth_gamma(mix_g, n)
    slack = candidates_slack(gamma)  # as Mixer.candidates
    candidates = np.array([1 + slack, 4 * eps, TINY]) / (1 - slack) * ROUNDING
    return np.array(
        [
            top_delta(gamma) * ROUNDING,
            top_floor(gamma, eps) * ROUNDING,
            *round_up32(candidates),
            top_delta(mix_gamma) * ROUNDING,
            top_floor(mix_gamma, eps) * ROUNDING,
            gamma64 / (1 - gamma64),
            eps,
        ]
    )
