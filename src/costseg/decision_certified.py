"""The certified fast path behind :mod:`costseg.decision` (see its docstring for the method).

float32 costs with a rounding certificate per pixel (``_Fast``, ``_top``), a float64 re-check of
the pixels left open (``_top64``), the float64 reference for true near ties (``_reference``), and
the mixing of vertex cost maps over a grid of mixtures (``_Mixer``; on the CPU, numba's kernel).
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable, Iterator

import torch

CPU_CHUNK = 32768  # pixels per chunk on the CPU: (V·N x chunk) float32 costs stay in cache
GPU_CHUNK = 1 << 21  # one 1024 x 2048 image
SETTLE_BLOCK = 1 << 16  # (mixture, pixel) pairs re-checked at once: (block x V x N) float64
U32, U64 = 2.0**-24, 2.0**-53  # unit roundoffs
INT_MAX, INF = 0x7FFFFFFF, 0x7F800000  # INF: bit pattern of float32 +inf (NaN lies above)
TINY = 2.0**-120  # absolute slack: covers float32 underflow (below N · 2**-149 per cost)


class _Fast:
    """Float32 costs of V matrices for one call, with their certified rounding bound.

    ``costs(q)``: (V, N + 1, P) = ``weight @ q`` for (N, P) float32 q. Rows ``:N`` use
    ``W = (C - C.min(0)) / π >= 0`` (global priors folded into the columns; argmin), row N is
    ``T = Σ_k R_k q_k`` with ``R = (C.max(0) - C.min(0) + |C|.max(0)) / π``, at least the
    magnitude of every reference cost. All terms are nonnegative, so each result errs by at most
    ``γ`` times its own value (plus underflow), the reference by at most ``eps · T``. ``γ``
    counts ``ρ``, the measured rounding of the matrix to float32 (a power-of-2 scale keeps it in
    range); two roundings of the inputs where matmuls may use TF32/bfloat16; three of q (casts,
    division by pixel-wise priors); ``γ_N = Nu / (1 - Nu)`` of a dot product of length N.
    """

    def __init__(self, matrices: torch.Tensor, probs: torch.Tensor, priors, eps: float) -> None:
        b, n, h, w = probs.shape
        self.probs, self.priors = probs.reshape(b, n, h * w), priors  # validated: (N,) or (N, H·W)
        matrices = matrices.cpu().double()  # small: prepared on the CPU, no GPU round trips
        low, high = matrices.amin(-2, keepdim=True), matrices.amax(-2, keepdim=True)
        weight = torch.cat([matrices - low, high - low + matrices.abs().amax(-2, True)], -2)
        self.weight64, self.rows = weight.reshape(-1, n), weight.shape[:2]  # for q = p / π
        if self.priors is not None and self.priors.ndim == 1:
            weight = weight / self.priors.double().cpu()
        top = weight.max().item()
        weight = weight * 2.0 ** -math.frexp(top)[1] if top > 0 else weight  # exact
        single = weight.float()
        rho = ((single.double() - weight).abs() / weight).nan_to_num(0).max().item() + 4 * U64
        precision = torch.get_float32_matmul_precision()
        if probs.device.type == "cuda" and torch.backends.cuda.matmul.allow_tf32:
            precision = "high" if precision == "highest" else precision
        self.u_in = {"highest": 0.0, "high": 2.0**-11, "medium": 2.0**-8}[precision]
        dot = n * U32 / (1 - n * U32)
        self.gamma = (1 + rho) * (1 + self.u_in) ** 2 * (1 + U32) ** 3 * (1 + dot) - 1
        # float64: one rounding of the matrix (minus C.min), one of q, the dot product.
        self.gamma64 = (1 + U64) ** 3 * (1 + n * U64 / (1 - n * U64)) - 1
        self.eps, self.folded = eps, weight  # folded: on the CPU, for decision_triton
        self.weight = single.reshape(-1, n).to(probs.device)
        self.weight64 = self.weight64.to(probs.device)
        low = (1 << max(1, (n - 1).bit_length())) - 1  # the bits that carry a class in _top
        self.code = torch.arange(n, dtype=torch.int32, device=probs.device).view(n, 1), low
        self.pixel_priors = None if priors is None or self.priors.ndim == 1 else self.priors

    def costs(self, q: torch.Tensor) -> torch.Tensor:
        """(N, P) float32 → (V, N + 1, P) float32: N costs (smaller = better), then T."""
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
        """Labels (R,) that float32 left open: stage 2 (float64 certificate), then stage 3.

        Args:
            q: (U, N) float64 ``p / π`` of the pixels (:meth:`exact_q`).
            shifted: (1, N, N) the reference's shifted matrix, or (K, N, N) with ``grid``.
            grid, inverse: None (R = U), or (R,) the mixture and the pixel of each label;
            weights: (K, V) float64 mixture weights.
        """
        costs = (q @ self.weight64.t()).view(len(q), *self.rows)
        if grid is None:
            return self._settle(q, costs[:, 0], self.gamma64, shifted)
        v, labels = self.rows[0], torch.empty_like(grid)
        gamma = (1 + self.gamma64) * (1 + v * U64 / (1 - v * U64)) - 1  # V more nonnegative terms
        for s in range(0, len(grid), SETTLE_BLOCK):
            k, pixel = grid[s : s + SETTLE_BLOCK], inverse[s : s + SETTLE_BLOCK]
            mixed = (weights[k, :, None] * costs[pixel]).sum(1)
            labels[s : s + SETTLE_BLOCK] = self._settle(q[pixel], mixed, gamma, shifted, k)
        return labels

    def _settle(self, q, costs, gamma: float, shifted, grid=None):
        """Stage 2 then 3 for (R, N) float64 q and their (R, N + 1) float64 costs and T."""
        labels, unsure = _top64(costs, gamma, self.eps)
        unsure = unsure.nonzero()[:, 0]
        if len(unsure):
            matrices = shifted if grid is None else shifted[grid[unsure]]
            labels[unsure] = _reference(q[unsure], matrices)
        return labels


class _Mixer:
    """Certified decisions of K mixtures, chunk by chunk (see the module docstring)."""

    def __init__(self, weights: torch.Tensor, fast: _Fast, mixed: torch.Tensor) -> None:
        self.weights64, self.weights, self.fast, self.mixed = weights, weights.float(), fast, mixed
        v = weights.shape[1]
        # Mixed costs (and T) sum V nonnegative terms: fast.gamma, w rounded to float32, the
        # matmul's inputs and a dot product of length V.
        dot = v * U32 / (1 - v * U32)
        self.gamma = (1 + fast.gamma) * (1 + U32) * (1 + fast.u_in) ** 2 * (1 + dot) - 1
        # Mixed signed differences (_signs): g for the costs, h for V + 4 roundings and inputs.
        g = fast.gamma / (1 - fast.gamma)
        h = (1 + U32) ** (v + 4) * (1 + fast.u_in) ** 2 - 1
        self.slack = (1.25 * (g + 2 * h), 2.5 * fast.eps * (1 + g))

    def chunk(self, costs: torch.Tensor, exact_q: Callable, labels: torch.Tensor) -> None:
        """Vertex costs (V, N + 1, P) of a chunk → its (K, P) labels."""
        fast, k, p = self.fast, len(self.weights), costs.shape[2]
        winner, open_ = _top(costs, fast.gamma, fast.eps, *fast.code)
        contested = ((winner != winner[:1]).any(0) | open_.any(0)).nonzero()[:, 0]
        if not len(contested):
            labels.copy_(winner[:1].expand(k, -1))
            return
        # Pixel j's labels will sit in column source[j] of table = [winner-0 labels, mixed]:
        # a gather, much faster than scattering K labels per contested pixel.
        table = torch.empty(k, p + len(contested), dtype=labels.dtype, device=labels.device)
        table[:, :p] = winner[:1]
        picked = costs.view(-1, p).index_select(1, contested).view(*costs.shape[:2], -1)
        order, grid, column = self._groups(picked, winner[:, contested].long(), table[:, p:])
        if len(grid):
            pixels, inverse = torch.unique(contested[order[column]], return_inverse=True)
            settled = fast.settle(exact_q(pixels), self.mixed, grid, self.weights64, inverse)
            table[grid, p + column] = settled.to(labels.dtype)
        source = torch.arange(p, device=labels.device)
        source[contested[order]] = p + torch.arange(len(order), device=labels.device)
        labels.copy_(table.gather(1, source.expand(k, -1)))

    def _groups(self, costs: torch.Tensor, winner: torch.Tensor, table: torch.Tensor):
        """Labels of contested pixels, grouped by their number of candidates, into ``table``.

        Returns:
            the pixels' order (P,) and the (mixture, column) pairs left open.
        """
        candidate = self._candidates(costs, winner)
        count = candidate.sum(0)
        k, v, n, p = *self.weights.shape, costs.shape[1] - 1, costs.shape[2]
        order, redo, start = [], [], 0
        for m in count.unique().tolist():
            sel = (count == m).nonzero()[:, 0]
            classes = candidate.index_select(1, sel).t().nonzero()[:, 1].view(-1, m).t()
            columns, order = table[:, start : start + len(sel)], [*order, sel]
            if m == 1:
                columns.copy_(classes.expand(k, -1))
            else:
                rows = torch.cat([classes, torch.full_like(classes[:1], n)])  # candidates, T
                picked = costs.view(v, -1).index_select(1, (rows * p + sel).flatten())
                method = self._signs if m <= 3 else self._many
                labels, unsure = method(picked.view(v, m + 1, -1), classes)
                columns.copy_(labels)
                screen = unsure.any(0).nonzero()[:, 0]  # open pairs are rare: screen pixels
                grid, column = unsure[:, screen].nonzero().unbind(1)
                redo.append(torch.stack([grid, screen[column] + start]))
            start += len(sel)
        redo = torch.cat(redo, 1) if redo else count.new_zeros(2, 0)
        return torch.cat(order), redo[0], redo[1]

    def _many(self, picked: torch.Tensor, classes: torch.Tensor):
        """(V, m + 1, P) candidate costs and T, (m, P) classes → labels (K, P), open (K, P)."""
        k, v = self.weights.shape
        mixed = (self.weights @ picked.view(v, -1)).view(k, len(picked[0]), -1)
        return _top(mixed, self.gamma, self.fast.eps, classes.int(), self.fast.code[1], True)

    def _signs(self, picked: torch.Tensor, classes: torch.Tensor):
        """``_many`` for two or three candidates: signs of mixed differences ``x_j - x_i``.

        Per pair i < j: ``lo = w · (d - s)`` and ``-hi = -w · (d + s)``, ``d = x_j - x_i``, with
        the slack ``s`` covering the rounding of x (relative to ``x_i + x_j``), of these float32
        operations and the reference's (``eps T``): ``lo > 0`` certifies i over j in the
        reference, ``-hi > 0`` j over i, never both. A class certified over all others wins.
        """
        (k, v), m = self.weights.shape, len(classes)
        *x, total = picked.unbind(1)
        rows = []
        for i, j in [(0, 1), (0, 2), (1, 2)][: 3 * (m - 2) + 1]:
            slack = torch.add((x[i] + x[j]).mul_(self.slack[0]), total, alpha=self.slack[1])
            slack += TINY
            rows += [x[j] - x[i] - slack, (x[j] - x[i] + slack).neg_()]
        signs = (self.weights @ torch.stack(rows, 1).view(v, -1)).view(k, len(rows), -1)
        if m == 2:
            wins = signs.unbind(1)  # a over b, b over a
        else:  # a over b and c, b over a and c, c over a and b
            wins = [torch.minimum(signs[:, i], signs[:, j]) for i, j in [(0, 2), (1, 4), (3, 5)]]
        best = functools.reduce(torch.maximum, wins)  # > 0: certain; NaN: not
        # The last class unless an earlier one wins (bit pattern >= 1: positive; -0.0 is INT_MIN).
        classes = classes.int()
        labels = classes[-1]
        for i in range(m - 1):
            won = wins[i].view(torch.int32).clamp(0, 1)
            labels = won.mul_(classes[i] - classes[-1]).add_(labels)
        return labels, ~(best > 0)

    def _candidates(self, costs: torch.Tensor, winner: torch.Tensor) -> torch.Tensor:
        """(N, P) bool: classes that no vertex winner beats in every vertex by a certain margin.

        A class beaten by the same class in every vertex is beaten at every mixture (w >= 0),
        in the reference too, so it can never be the decision. "Certain": ``x_j - x_a`` exceeds
        twice the rounding of both (relative) and of the reference (``eps T``).
        """
        costs, total = costs[:, :-1], costs[:, -1:]
        slack = 2 * self.fast.gamma / (1 - self.fast.gamma) * 1.01  # 1.01: this test's rounding
        extra = total * (4 * self.fast.eps) + TINY
        beaten = None  # max over winners a of min over vertices of x_j - threshold_a (> 0: beaten)
        for best in winner:
            chosen = costs.gather(1, best.expand(costs.shape[0], 1, -1))
            margin = (costs - (chosen * (1 + slack) + extra) / (1 - slack)).amin(0)
            beaten = margin if beaten is None else torch.maximum(beaten, margin)
        return ~(beaten > 0)  # NaN: a candidate


def _top(
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
    ``x_b - x_a > Δ x_b`` with ``Δ = 2.5γ / (1 - γ)`` (2γ for both roundings, γ/2 left for the
    reference's), ``x_b >= 10 eps T / γ`` and ``x_b >= 2**-60`` (underflow then negligible).

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
    packed = packed.bitwise_and_(INT_MAX - low) if inplace else packed & (INT_MAX - low)
    best = packed.bitwise_or_(code).amin(-2, keepdim=True)
    # packed - best - 1 >= 0 except at the best (-1, masked to INT_MAX): the gap minus one.
    gap = torch.sub(packed, best + 1, out=packed).bitwise_and_(INT_MAX).amin(-2)
    best = best.squeeze(-2)
    delta = 2.5 * gamma / (1 - gamma)
    limit = math.ceil(delta * 2**24 / (1 - delta)) + 2 * low + 1
    # Every other cost's bits are >= best + gap + 1 - low: a lower bound, inf or NaN past INF.
    lower = best + torch.minimum(gap, INF - best) + (1 - low)
    floor = torch.add(2.0**-60, total, alpha=10 * eps / gamma)
    certain = (gap >= limit) & (lower.view(torch.float32) >= floor) & (lower < INF - low)
    return torch.bitwise_and(best, low, out=out), ~certain


def _top64(costs: torch.Tensor, gamma: float, eps: float) -> tuple[torch.Tensor, torch.Tensor]:
    """``_top`` for (R, N + 1) float64 costs (argmin over dim 1, last column T), in floats.

    Certified when ``x_b - x_a - g (x_a + x_b)`` (a lower bound on ``y_b - y_a``) exceeds the
    reference's ``2 eps T (1 + g)``, ``g = γ / (1 - γ)``; 1.25 and ``1 - 4u`` absorb the
    rounding of the test itself, ``2**-900`` underflow.
    """
    if costs.shape[1] == 2:  # one class
        return torch.zeros_like(costs[:, 0], dtype=torch.long), torch.zeros_like(costs[:, 0] > 0)
    costs, total = costs[:, :-1], costs[:, -1]
    lo, index = costs.min(1, keepdim=True)  # the first minimum
    hi = costs.scatter(1, index, math.inf).amin(1)
    g, lo = gamma / (1 - gamma), lo[:, 0]
    need = 1.25 * (g * (lo + hi) + 2 * eps * (1 + g) * total) + 2.0**-900
    return index[:, 0], ~((hi - lo) * (1 - 4 * U64) > need)


def _reference(q: torch.Tensor, shifted: torch.Tensor) -> torch.Tensor:
    """The reference: (R, N) float64 q and (R or 1, N, N) shifted matrices → (R,) labels."""
    costs = torch.zeros(q.shape[0], shifted.shape[1], dtype=torch.float64, device=q.device)
    for k in range(q.shape[1]):  # ascending k, product and sum each rounded once
        costs = costs + shifted[:, :, k] * q[:, k, None]
    return costs.min(1).indices  # first minimum: ties to the lowest index
