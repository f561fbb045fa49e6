"""Stage 1 of :mod:`costseg.decision` on a GPU: one Triton kernel, one read of the probabilities.

Each program takes a block of pixels, sums the cost rows of V vertex matrices (N costs and the
bound T, ``_Fast``'s nonnegative weights, global priors folded in) in registers, then for each
of K mixtures ``Σ_v w_kv x_v`` (``decide``: K = V = 1, w = 1) finds the argmin ``a``, the
runner-up ``x_b`` and ``_top64``'s certificate ``x_b - x_a - g (x_a + x_b) > 2 eps T (1 + g)``
(``g = γ / (1 - γ)``, with its margins; the test in float64, T finite). It writes one label and
one open flag per pixel and mixture; no cost map reaches memory. Costs are summed in float64
(``FLOAT64``, the default: the H100 / H200 run float64 at half their float32 rate, and only true
near ties stay open) or float32. The open pairs go to the float64 stages of
:mod:`costseg.decision`.
"""

from __future__ import annotations

import torch
import triton
import triton.language as tl

U32, U64 = 2.0**-24, 2.0**-53
BLOCK = 128  # pixels per program: V x rows x BLOCK partial costs live in registers


@triton.jit
def _certified_argmin(
    probs,  # (N, P) any float
    weight,  # (VP, R, N) compute dtype, zero rows past N + 1 and past V
    mix,  # (K, VP) compute dtype, zero past V
    labels,  # (K, P) integer
    opened,  # (K, P) int8
    P,
    K,
    g,
    slack,
    tiny,
    N: tl.constexpr,
    R: tl.constexpr,
    VP: tl.constexpr,
    BLOCK: tl.constexpr,
    FLOAT64: tl.constexpr,
):
    dtype = tl.float64 if FLOAT64 else tl.float32
    offs = tl.program_id(0).to(tl.int64) * BLOCK + tl.arange(0, BLOCK)
    inside = offs < P
    rows = tl.arange(0, R)
    verts = tl.arange(0, VP)
    costs = tl.zeros((VP, R, BLOCK), dtype)
    row = probs + offs  # pointers step by P (64-bit: K x P may pass 2**31)
    for k in range(N):
        x = tl.load(row, mask=inside, other=0.0).to(dtype)
        w = tl.load(weight + (verts[:, None] * R + rows[None, :]) * N + k)
        costs += w[:, :, None] * x[None, None, :]
        row += P
    out, flag = labels + offs, opened + offs
    for m in range(K):
        w = tl.load(mix + m * VP + verts)
        mixed = tl.sum(w[:, None, None] * costs, axis=0)  # (R, BLOCK)
        total = tl.sum(tl.where(rows[:, None] == N, mixed, 0.0), axis=0)
        mixed = tl.where(rows[:, None] < N, mixed, float("inf"))
        best = tl.min(mixed, axis=0)
        arg = tl.argmin(mixed, axis=0)
        second = tl.min(tl.where(rows[:, None] == arg[None, :], float("inf"), mixed), axis=0)
        lo, hi, t = best.to(tl.float64), second.to(tl.float64), total.to(tl.float64)
        need = 1.25 * (g * (lo + hi) + slack * t) + tiny
        ok = ((hi - lo) * (1 - 2.0**-51) > need) & (t < float("inf"))
        tl.store(out, arg.to(labels.dtype.element_ty), mask=inside)
        tl.store(flag, (~ok).to(tl.int8), mask=inside)
        out += P
        flag += P


def certified_argmin(
    probs: torch.Tensor,
    weight: torch.Tensor,
    mix: torch.Tensor,
    eps: float,
    labels: torch.Tensor,
    float64: bool = True,
) -> torch.Tensor:
    """Labels of K mixtures of V matrices for one image's pixels, and where they are open.

    Args:
        probs: (N, P) probabilities (float16 / bfloat16 / float32), contiguous.
        weight: (V, N + 1, N) float64 nonnegative rows and T (``_Fast.folded``: priors folded,
            scaled), best on the CPU.
        mix: (K, V) float64 mixture weights >= 0 (``[[1.0]]`` for one matrix), best on the CPU.
        eps: the reference's rounding per T.
        labels: (K, P) integer output.

    Returns:
        (K, P) bool: open pairs (their labels are meaningless).
    """
    (v, rows, n), k, probs = weight.shape, len(mix), probs.contiguous()
    weight, mix = weight.cpu(), mix.cpu()  # small: prepared on the CPU, no GPU round trips
    dtype, u = (torch.float64, U64) if float64 else (torch.float32, U32)
    vp, r = triton.next_power_of_2(v), max(16, triton.next_power_of_2(rows))
    padded = weight.new_zeros(vp, r, n, dtype=dtype)
    padded[:v, :rows] = weight
    mixing = mix.new_zeros(k, vp, dtype=dtype)
    mixing[:, :v] = mix
    # Nonnegative sums of N terms per vertex cost, then V per mixture, in the compute dtype; the
    # weights' float64 construction (4 U64, as in _Fast) and rounding to it (ρ), one rounding of
    # q (exact from float16/bfloat16/float32) and of the mixture weights.
    rho = ((padded[:v, :rows].double() - weight).abs() / weight).nan_to_num(0).max().item()
    dot = (n + v) * u / (1 - (n + v) * u)
    gamma = (1 + rho + 4 * U64) * (1 + u) ** 2 * (1 + dot) - 1
    g = gamma / (1 - gamma)
    tiny = 2.0**-900 if float64 else 2.0**-60  # far above the sums' underflow
    padded, mixing = padded.to(probs.device), mixing.to(probs.device)
    opened = torch.empty(labels.shape, dtype=torch.int8, device=probs.device)
    grid = (triton.cdiv(probs.shape[1], BLOCK),)
    _certified_argmin[grid](
        probs, padded, mixing, labels, opened, probs.shape[1], k, g, 2 * eps * (1 + g), tiny,
        N=n, R=r, VP=vp, BLOCK=BLOCK, FLOAT64=float64,
    )  # fmt: skip
    return opened.bool()
