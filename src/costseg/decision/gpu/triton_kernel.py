"""Stage 1 of the decision layer on a GPU: one Triton kernel, one read of the probabilities.

Each program takes a block of pixels, sums the cost rows of V vertex matrices (M costs: N
classes, and deferring where the matrices have a defer row; then the bound T,
``CertifiedCosts``' nonnegative weights, global priors folded in) in registers, then
for each of K mixtures ``Σ_v w_kv x_v`` (``decide``: K = V = 1, w = 1) finds the argmin ``a``,
the runner-up ``x_b`` and the certificate ``x_b - x_a - g (x_a + x_b) > 2 eps T (1 + g)``
(``g = γ / (1 - γ)``, with its margins; the test in float64, T finite). It writes one label and
one open flag per pixel and mixture, and counts the open pairs; no cost map reaches memory.

The M + 1 rows are held as two tiles of power-of-2 sizes (16 + 4 for M = 19), not one of 32.
Where every vertex's winner is the same and certified with the mixtures' margins on every pixel
of a block, each mixture's certificate holds too (it is linear in the vertex costs, the weights
are nonnegative), and the block writes that winner for all K without mixing. Costs are summed in
float64 (``FLOAT64``, the default: only true near ties stay open) or float32. The open pairs go
to the float64 stages (``CertifiedCosts.settle``).
"""

from __future__ import annotations

import functools

import torch
import triton
import triton.language as tl

from costseg.decision import certificate as cert

# the float64 certificate's own rounding (constexpr: a kernel reads no other globals)
MARGIN, SHRINK = tl.constexpr(cert.TEST_MARGIN), tl.constexpr(cert.GAP_SHRINK)
# (pixels per program, warps) for one vertex and for several (more costs per pixel in registers;
# small blocks take the every-vertex-agrees shortcut more often): the fastest measured on an H200
CONFIG = [(256, 2), (32, 1)]


@triton.jit
def _best_two(costs_a, costs_b, RA: tl.constexpr, RB: tl.constexpr, M: tl.constexpr):
    """Argmin, best, runner-up and T (row M) of costs held as (RA, BLOCK) and (RB, BLOCK)."""
    rows_a, rows_b = tl.arange(0, RA)[:, None], tl.arange(0, RB)[:, None]
    total = tl.sum(tl.where(rows_a == M, costs_a, 0.0), 0)
    total += tl.sum(tl.where(rows_b + RA == M, costs_b, 0.0), 0)
    costs_a = tl.where(rows_a < M, costs_a, float("inf"))
    costs_b = tl.where(rows_b + RA < M, costs_b, float("inf"))
    best_a, arg_a = tl.min(costs_a, 0), tl.argmin(costs_a, 0)
    best_b, arg_b = tl.min(costs_b, 0), tl.argmin(costs_b, 0)
    second_a = tl.min(tl.where(rows_a == arg_a[None, :], float("inf"), costs_a), 0)
    second_b = tl.min(tl.where(rows_b == arg_b[None, :], float("inf"), costs_b), 0)
    in_b = best_b < best_a
    best = tl.where(in_b, best_b, best_a)
    arg = tl.where(in_b, arg_b + RA, arg_a)
    second = tl.where(in_b, tl.minimum(best_a, second_b), tl.minimum(second_a, best_b))
    return arg, best, second, total


@triton.jit
def _certified(best, second, total, g, slack, tiny):
    """``certificate.certified64`` in float64."""
    lo, hi, t = best.to(tl.float64), second.to(tl.float64), total.to(tl.float64)
    need = MARGIN * (g * (lo + hi) + slack * t) + tiny
    return ((hi - lo) * SHRINK > need) & (t < float("inf"))


@triton.jit
def _add_column(costs_a, costs_b, row, weight, k, rows_a, rows_b, inside, dtype, stride):
    """Add column k of the weights times the pixels' q_k (at ``row``) to both tiles."""
    x = tl.load(row, mask=inside, other=0.0).to(dtype)[None, None, :]
    costs_a += tl.load(weight + k * stride + rows_a)[:, :, None] * x
    costs_b += tl.load(weight + k * stride + rows_b)[:, :, None] * x
    return costs_a, costs_b


@triton.jit
def _certified_argmin(
    probs,  # (N, P) any float
    weight,  # (N, VP, RA + RB) compute dtype: column k of every vertex's rows, zero padded
    mix,  # (K, VP) compute dtype, zero past V
    labels,  # (K, P) integer
    opened,  # (K, P) int8
    count,  # (1,) int64: open pairs, added to
    scalars,  # (4,) float64: g, slack, tiny, vertex_tiny (see Rule)
    P,
    K,
    N: tl.constexpr,
    M: tl.constexpr,
    RA: tl.constexpr,
    RB: tl.constexpr,
    V: tl.constexpr,
    VP: tl.constexpr,
    BLOCK: tl.constexpr,
    FLOAT64: tl.constexpr,
    UNROLL: tl.constexpr,
):
    dtype = tl.float64 if FLOAT64 else tl.float32
    g, slack = tl.load(scalars), tl.load(scalars + 1)
    tiny, vertex_tiny = tl.load(scalars + 2), tl.load(scalars + 3)
    offs = tl.program_id(0).to(tl.int64) * BLOCK + tl.arange(0, BLOCK)
    inside = offs < P
    verts = tl.arange(0, VP)[:, None]
    rows_a, rows_b = verts * (RA + RB) + tl.arange(0, RA)[None, :], tl.arange(0, RB)[None, :]
    rows_b += verts * (RA + RB) + RA
    costs_a = tl.zeros((VP, RA, BLOCK), dtype)
    costs_b = tl.zeros((VP, RB, BLOCK), dtype)
    row = probs + offs  # pointers step by P (64-bit: K x P may pass 2**31)
    if UNROLL:  # one vertex: the weights' loads scheduled freely
        for k in tl.static_range(N):
            costs_a, costs_b = _add_column(costs_a, costs_b, row + k * P, weight, k, rows_a, rows_b,
                                           inside, dtype, VP * (RA + RB))  # fmt: skip
    else:  # several: a loop keeps V x (M + 1) x BLOCK costs, not the weights, in registers
        for k in range(N):
            costs_a, costs_b = _add_column(costs_a, costs_b, row + k * P, weight, k, rows_a, rows_b,
                                           inside, dtype, VP * (RA + RB))  # fmt: skip
    out, flag = labels + offs, opened + offs
    # Every vertex's winner certified with the mixtures' margins (vertex_tiny: tiny over the
    # smallest sum of a mixture's weights) certifies it for every mixture.
    first, best, second, total = _best_two(
        tl.sum(tl.where(verts[:, :, None] == 0, costs_a, 0.0), 0),
        tl.sum(tl.where(verts[:, :, None] == 0, costs_b, 0.0), 0), RA, RB, M,
    )  # fmt: skip
    agree = inside & _certified(best, second, total, g, slack, vertex_tiny)
    for v in tl.static_range(1, V):
        vertex_a = tl.sum(tl.where(verts[:, :, None] == v, costs_a, 0.0), 0)
        vertex_b = tl.sum(tl.where(verts[:, :, None] == v, costs_b, 0.0), 0)
        arg, best, second, total = _best_two(vertex_a, vertex_b, RA, RB, M)
        agree &= _certified(best, second, total, g, slack, vertex_tiny) & (arg == first)
    if tl.min(tl.where(inside, agree, True).to(tl.int32), 0) == 1:
        for _ in range(K):
            tl.store(out, first.to(labels.dtype.element_ty), mask=inside)
            tl.store(flag, tl.zeros((BLOCK,), tl.int8), mask=inside)
            out += P
            flag += P
    else:
        unsure = tl.zeros((BLOCK,), tl.int32)
        for m in range(K):
            w = tl.load(mix + m * VP + verts)[:, :, None]
            mixed_a, mixed_b = tl.sum(w * costs_a, 0), tl.sum(w * costs_b, 0)
            arg, best, second, total = _best_two(mixed_a, mixed_b, RA, RB, M)
            ok = _certified(best, second, total, g, slack, tiny) | ~inside
            tl.store(out, arg.to(labels.dtype.element_ty), mask=inside)
            tl.store(flag, (~ok).to(tl.int8), mask=inside)
            unsure += (~ok).to(tl.int32)
            out += P
            flag += P
        some = tl.sum(unsure, 0)
        if some > 0:
            tl.atomic_add(count, some.to(tl.int64))


class Rule:
    """The kernel's arguments for V vertex matrices and K mixtures, prepared once (:func:`rule`).

    Call with (N, P) probabilities (float16 / bfloat16 / float32, contiguous) and (K, P) integer
    labels to fill; returns the (K, P) int8 open flags, or None where no pair is open (one
    synchronisation: reading the count).
    """

    def __init__(self, weight: torch.Tensor, mix: torch.Tensor, eps: float, float64: bool, device):
        (v, rows, n), k = weight.shape, len(mix)
        dtype, u = (torch.float64, cert.U64) if float64 else (torch.float32, cert.U32)
        vp = triton.next_power_of_2(v)
        ra = triton.next_power_of_2(rows + 1) // 2  # the largest power of 2 <= rows
        rb = triton.next_power_of_2(max(1, rows - ra))
        padded = weight.new_zeros(vp, ra + rb, n, dtype=dtype)
        padded[:v, :rows] = weight
        mixing = mix.new_zeros(k, vp, dtype=dtype)
        mixing[:, :v] = mix
        # ρ: the weights' rounding to the compute dtype (q is exact from float16/bfloat16/float32)
        rho = ((padded[:v, :rows].double() - weight).abs() / weight).nan_to_num(0).max().item()
        gamma = cert.kernel_gamma(rho, n, v, u)
        g = gamma / (1 - gamma)
        tiny = cert.FLOOR64 if float64 else cert.FLOOR32  # far above the sums' underflow
        params = [g, 2 * eps * (1 + g), tiny, tiny / mix.sum(1).min().item()]
        self.scalars = torch.tensor(params, dtype=torch.float64).to(device)
        self.weight = padded.permute(2, 0, 1).contiguous().to(device)
        self.mix = mixing.to(device)
        self.shape = dict(N=n, M=rows - 1, RA=ra, RB=rb, V=v, VP=vp, FLOAT64=float64, UNROLL=v == 1)

    def __call__(self, probs: torch.Tensor, labels: torch.Tensor):
        opened = torch.empty(labels.shape, dtype=torch.int8, device=probs.device)
        count = torch.zeros(1, dtype=torch.long, device=probs.device)  # per call: rules are shared
        block, warps = CONFIG[self.shape["V"] > 1]
        grid = (triton.cdiv(probs.shape[1], block),)
        _certified_argmin[grid](
            probs, self.weight, self.mix, labels, opened, count, self.scalars, probs.shape[1],
            len(self.mix), **self.shape, BLOCK=block, num_warps=warps,
        )  # fmt: skip
        return opened if count.item() else None


@functools.lru_cache(maxsize=32)
def _cached(weight: bytes, shape: tuple, mix: bytes, k: int, eps: float, float64: bool, device):
    weight_t = torch.frombuffer(bytearray(weight), dtype=torch.float64).view(shape)
    mix_t = torch.frombuffer(bytearray(mix), dtype=torch.float64).view(k, shape[0])
    return Rule(weight_t, mix_t, eps, float64, device)


def rule(weight: torch.Tensor, mix: torch.Tensor, eps: float, device, float64: bool = True) -> Rule:
    """The prepared kernel for (V, M + 1, N) float64 nonnegative rows and T
    (``CertifiedCosts.folded``: priors folded, scaled; on the CPU) and (K, V) float64 mixture
    weights >= 0 (``[[1.0]]`` for one matrix), cached per matrix, weights and device: preparing
    it copies to the GPU."""
    weight, mix = weight.detach().double().contiguous(), mix.detach().double().cpu().contiguous()
    key = (weight.numpy().tobytes(), tuple(weight.shape), mix.numpy().tobytes(), len(mix))
    return _cached(*key, eps, float64, torch.device(device))
