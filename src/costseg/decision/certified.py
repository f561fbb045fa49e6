"""Certified costs, shared by every fast path (docs/definitions.md §1).

Stage 1 of a fast path computes costs in float32 (or, on a GPU, float64 in registers) with the
nonnegative matrix of :class:`CertifiedCosts`, whose rounding bound ``γ`` certifies the
reference's decision where the gap between the best two is wide enough (:func:`top`). The pixels
left open go to :meth:`CertifiedCosts.settle`: stage 2, the same certificate on float64 costs
(:func:`top64`), then stage 3, the reference itself (:func:`~.reference.reference_labels`).
"""

from __future__ import annotations

import copy
import functools
import math
from collections.abc import Callable, Iterator

import torch

from costseg.costs import mix_costs
from costseg.decision import certificate as cert
from costseg.decision.label_maps import empty_labels
from costseg.decision.reference import reference_labels, shift

CPU_CHUNK = 32768  # pixels per chunk on the CPU: (V·N x chunk) float32 costs stay in cache
GPU_CHUNK = 1 << 21  # one 1024 x 2048 image
SETTLE_BLOCK = 1 << 16  # (mixture, pixel) pairs re-checked at once: (block x V x N) float64


class CertifiedCosts:
    """Float32 costs of V matrices for one call, with their certified rounding bound.

    ``costs(q)``: (V, M + 1, P) = ``weight @ q`` for (N, P) float32 q, M rows of C (M = N, or
    N + 1 with a defer row: one more candidate). Rows ``:M`` use
    ``W = (C - C.min(0)) / π >= 0`` (global priors folded into the columns; argmin), row M is
    ``T = Σ_k R_k q_k`` with ``R = (C.max(0) - C.min(0) + |C|.max(0)) / π``, at least the
    magnitude of every reference cost. All terms are nonnegative, so each result errs by at most
    ``γ`` times its own value (plus underflow), the reference by at most ``eps · T``. ``γ``
    (:func:`~.certificate.costs_gamma`) counts ``ρ``, the measured rounding of the matrix to
    float32 (a power-of-2 scale keeps it in range).

    Args:
        matrices: (V, M, N) float64 cost matrices; probs: (B, N, H, W);
        priors: None, (N,) or (N, H·W); eps: the reference's rounding per T.
    """

    def __init__(self, matrices: torch.Tensor, probs: torch.Tensor, priors, eps: float) -> None:
        b, n, h, w = probs.shape
        self.probs, self.priors = probs.reshape(b, n, h * w), priors
        matrices = matrices.cpu().double()  # small: prepared on the CPU, no GPU round trips
        low, high = matrices.amin(-2, keepdim=True), matrices.amax(-2, keepdim=True)
        weight = torch.cat([matrices - low, high - low + matrices.abs().amax(-2, True)], -2)
        self.weight64, self.rows = weight.reshape(-1, n), weight.shape[:2]  # for q = p / π
        if self.priors is not None and self.priors.ndim == 1:
            weight = weight / self.priors.double().cpu()
        top_ = weight.max().item()
        weight = weight * 2.0 ** -math.frexp(top_)[1] if top_ > 0 else weight  # exact
        single = weight.float()
        rho = ((single.double() - weight).abs() / weight).nan_to_num(0).max().item() + 4 * cert.U64
        precision = torch.get_float32_matmul_precision()
        if probs.device.type == "cuda" and torch.backends.cuda.matmul.allow_tf32:
            precision = "high" if precision == "highest" else precision
        self.u_in = cert.MATMUL_INPUT_ROUNDING[precision]
        self.gamma, self.gamma64 = cert.costs_gamma(rho, self.u_in, n), cert.costs_gamma64(n)
        self.eps, self.folded = eps, weight  # folded: on the CPU, for the Triton kernel
        self.weight = single.reshape(-1, n).to(probs.device)
        self.weight64 = self.weight64.to(probs.device)
        m = self.rows[1] - 1  # candidates: classes (and deferring)
        low = (1 << max(1, (m - 1).bit_length())) - 1  # the bits that carry a row in top()
        self.code = torch.arange(m, dtype=torch.int32, device=probs.device).view(m, 1), low
        self.pixel_priors = None if priors is None or self.priors.ndim == 1 else self.priors

    @property
    def read_as_is(self) -> bool:
        """A float32 image without pixel-wise priors: compiled kernels read its q where it lies
        (q is p, global priors folded into their weights)."""
        return self.probs.dtype == torch.float32 and self.pixel_priors is None

    def costs(self, q: torch.Tensor) -> torch.Tensor:
        """(N, P) float32 → (V, M + 1, P) float32: M costs (smaller = better), then T."""
        return (self.weight @ q).view(*self.rows, -1)

    def exact_q(self, image: int, pixels: torch.Tensor) -> torch.Tensor:
        """(R, N) float64 ``p / π`` of the given pixels of one image, as the reference has it."""
        q = self.probs[image].index_select(1, pixels).double()
        if self.priors is not None:
            prior = self.priors[:, None] if self.priors.ndim == 1 else self.priors[:, pixels]
            q = q / prior.double()
        return q.t()

    def chunks(self, image: int, step: int | None = None) -> Iterator[tuple[int, torch.Tensor]]:
        """(first pixel, (N, P) float32 q) for every chunk of ``step`` pixels of one image."""
        probs = self.probs[image]
        step = step or (CPU_CHUNK if probs.device.type == "cpu" else GPU_CHUNK)
        for s in range(0, probs.shape[1], step):
            q = probs[:, s : s + step]
            if self.pixel_priors is not None:
                q = q.float() / self.pixel_priors[:, s : s + step].float()
            yield s, q.float()

    def settle(self, q: torch.Tensor, shifted: torch.Tensor, grid=None, weights=None, inverse=None):
        """Labels (R,) that stage 1 left open: stage 2 (float64 certificate), then stage 3.

        Args:
            q: (U, N) float64 ``p / π`` of the pixels (:meth:`exact_q`).
            shifted: (1, M, N) the reference's shifted matrix, or (K, M, N) with ``grid``.
            grid, inverse: None (R = U), or (R,) the mixture and the pixel of each label;
            weights: (K, V) float64 mixture weights.
        """
        costs = (q @ self.weight64.t()).view(len(q), *self.rows)
        if grid is None:
            return self._settle(q, costs[:, 0], self.gamma64, shifted)
        labels = torch.empty_like(grid)
        gamma = cert.more_terms(self.gamma64, self.rows[0])  # V more nonnegative terms
        for s in range(0, len(grid), SETTLE_BLOCK):
            k, pixel = grid[s : s + SETTLE_BLOCK], inverse[s : s + SETTLE_BLOCK]
            mixed = (weights[k, :, None] * costs[pixel]).sum(1)
            labels[s : s + SETTLE_BLOCK] = self._settle(q[pixel], mixed, gamma, shifted, k)
        return labels

    def _settle(self, q, costs, gamma: float, shifted, grid=None):
        """Stage 2 then 3 for (R, N) float64 q and their (R, M + 1) float64 costs and T."""
        labels, unsure = top64(costs, gamma, self.eps)
        unsure = unsure.nonzero()[:, 0]
        if len(unsure):
            matrices = shifted if grid is None else shifted[grid[unsure]]
            labels[unsure] = reference_labels(q[unsure], matrices)
        return labels


def prepare(matrices: torch.Tensor, probs: torch.Tensor, priors, eps: float) -> CertifiedCosts:
    """``CertifiedCosts(matrices, probs, priors, eps)`` for (N,) or (N, H, W) priors; the matrix
    part is prepared once per matrices, global priors, device and matmul precision (small copies
    to a GPU cost more than the kernel)."""
    if priors is not None and priors.ndim > 1:
        return CertifiedCosts(matrices, probs, priors.reshape(len(priors), -1), eps)
    key = None if priors is None else priors.detach().double().cpu().numpy().tobytes()
    precision = torch.get_float32_matmul_precision(), torch.backends.cuda.matmul.allow_tf32
    template = _template(
        matrices.detach().numpy().tobytes(), matrices.shape, key, eps, probs.device, precision
    )
    fast = copy.copy(template)
    fast.probs, fast.priors = probs.reshape(*probs.shape[:2], -1), priors
    return fast


@functools.lru_cache(maxsize=64)
def _template(matrices: bytes, shape, priors: bytes | None, eps: float, device, precision):
    """A ``CertifiedCosts`` of these matrices and global priors for a stand-in image."""
    as_tensor = lambda data: torch.frombuffer(bytearray(data), dtype=torch.float64)  # noqa: E731
    matrices = as_tensor(matrices).view(shape)
    priors = None if priors is None else as_tensor(priors).to(device)
    return CertifiedCosts(matrices, torch.empty(1, shape[-1], 1, 1, device=device), priors, eps)


def single_rule(probs: torch.Tensor, cost: torch.Tensor, priors) -> tuple:
    """A single rule's certified costs, its (B, H·W) int64 rows to fill, and a function that
    returns the reference's (1, M, N) shifted matrix (built once, where one is needed)."""
    fast = prepare(cost, probs, priors, cert.reference_eps(probs.shape[1], mixtures=False))
    b, _, h, w = probs.shape
    out = empty_labels(b, h * w, dtype=torch.long, device=probs.device)
    return fast, out, functools.cache(lambda: shift(cost).to(probs.device))


def mixtures(probs: torch.Tensor, vertices: torch.Tensor, weights: torch.Tensor, priors) -> tuple:
    """The vertices' certified costs, (B, K, H·W) rows to fill (uint8 for N <= 256: K label maps
    add up, else int64; a defer row, N, fits: N <= 255), and functions that return the mixed
    matrices' (K, M, N) shifted matrices and the (K, V) float64 weights on the probabilities'
    device (built where needed)."""
    n = probs.shape[1]
    fast = prepare(vertices.double().cpu(), probs, priors, cert.reference_eps(n, mixtures=True))
    b, _, h, w = probs.shape
    dtype = torch.uint8 if n <= 256 else torch.long
    out = empty_labels(b, len(weights), h * w, dtype=dtype, device=probs.device)
    mixed = functools.cache(lambda: shift(mix_costs(vertices, weights).to(probs.device)))
    weights64 = functools.cache(lambda: weights.to(probs.device, torch.float64))
    return fast, out, mixed, weights64


def decide_in_chunks(
    fast: CertifiedCosts, out: torch.Tensor, step: int | None, chunk: Callable, shifted: Callable
) -> None:
    """One rule, image by image and chunk by chunk: ``chunk(q, labels)`` writes a chunk's labels
    and returns the pixels it left open, which :meth:`CertifiedCosts.settle` decides.

    Args:
        out: (B, H·W) labels, written; step: pixels per chunk (None: the default);
        shifted: returns the reference's (1, M, N) shifted matrix (built where one is needed).
    """
    for i in range(len(out)):
        redo, q64 = [], []
        for s, q in fast.chunks(i, step):
            redo.append(chunk(q, out[i, s : s + q.shape[1]]) + s)
            q64.append(fast.exact_q(i, redo[-1]))  # while the chunk is in cache
        redo = torch.cat(redo)
        if len(redo):
            out[i, redo] = fast.settle(torch.cat(q64), shifted())


def top(
    costs: torch.Tensor,
    gamma: float,
    eps: float,
    code: torch.Tensor,
    low: int,
    inplace: bool = False,
    out: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Argmin over dim -2 of float32 costs >= 0 whose last row is T, and where it is open.

    With computed costs x, exact y, ``|x - y| <= γ y`` and the reference within ``eps T`` of y
    (up to a per-pixel constant), the argmin a and the runner-up b satisfy
    ``y_b - y_a > 2 eps T`` -- so the reference decides a, uniquely -- when
    ``x_b - x_a > Δ x_b`` (``Δ``: :func:`~.certificate.top_delta`), ``x_b >= 10 eps T / γ`` and
    ``x_b >= FLOOR32`` (underflow then negligible).

    Nonnegative floats order like their int32 bit patterns, whose low bits (mask ``low``) carry
    ``code``, the rows' labels ((m, 1) or (m, P) int32 <= low; lowest wins ties). n ulps above a
    value lie at least ``n · 2**-24`` times it above; clearing the low bits moves a pattern by at
    most ``low``.

    Returns:
        (..., P) ``code`` of the argmin (int32, or written to ``out``) and (..., P) bool: open
        (also inf, NaN). With ``inplace``, ``costs`` is overwritten.
    """
    costs, total = costs[..., :-1, :], costs[..., -1, :]
    packed = costs.view(torch.int32)
    mask = cert.INT_MAX - low
    packed = packed.bitwise_and_(mask) if inplace else packed & mask
    best = packed.bitwise_or_(code).amin(-2, keepdim=True)
    # packed - best - 1 >= 0 except at the best (-1, masked to INT_MAX): the gap minus one.
    gap = torch.sub(packed, best + 1, out=packed).bitwise_and_(cert.INT_MAX).amin(-2)
    best = best.squeeze(-2)
    delta = cert.top_delta(gamma)
    limit = math.ceil(delta * 2**24 / (1 - delta)) + 2 * low + 1
    # Every other cost's bits are >= best + gap + 1 - low: a lower bound, inf or NaN past INF.
    lower = best + torch.minimum(gap, cert.INF_BITS - best) + (1 - low)
    floor = torch.add(cert.FLOOR32, total, alpha=cert.top_floor(gamma, eps))
    certain = (gap >= limit) & (lower.view(torch.float32) >= floor) & (lower < cert.INF_BITS - low)
    return torch.bitwise_and(best, low, out=out), ~certain


def top64(costs: torch.Tensor, gamma: float, eps: float) -> tuple[torch.Tensor, torch.Tensor]:
    """``top`` for (R, M + 1) float64 costs (argmin over dim 1, last column T), in floats, with
    :func:`~.certificate.certified64`; returns labels (R,) and open (R,)."""
    if costs.shape[1] == 2:  # one class
        return torch.zeros_like(costs[:, 0], dtype=torch.long), torch.zeros_like(costs[:, 0] > 0)
    costs, total = costs[:, :-1], costs[:, -1]
    lo, index = costs.min(1, keepdim=True)  # the first minimum
    hi = costs.scatter(1, index, math.inf).amin(1)
    return index[:, 0], ~cert.certified64(lo[:, 0], hi, total, gamma / (1 - gamma), eps)
