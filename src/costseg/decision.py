"""The decision layer: per-pixel argmin of expected cost (SPEC §1), fast and exact.

``d(x; C) = argmin_k' Σ_k C[k', k] · p(k|x) / π(k)``, ties to the lowest class index.

**The reference** (the float64 evaluation every decision equals, bit for bit): each column of
``C`` is shifted by its largest entry, ``Cs = C - C.max(0)`` in float64 (a column constant
changes every row's cost equally, hence no decision); ``q = p / π`` in float64; the costs
``Σ_k Cs[k', k] · q_k`` are summed over k in ascending order, one rounded product and one
rounded sum at a time; argmin with ties to the lowest index. The shift turns the symmetric
matrix into ``-λI``: its costs are ``-λ q`` rounded monotonically, so exact ties in ``q`` stay
exact and the robotistic rule *is* argmax.

**The fast path** gives the same decisions on every pixel (probabilities must be >= 0):

* costs in float32, one matmul per chunk of pixels (CPU: chunks that stay in cache; GPU: whole
  images), with ``W = (C.max(0) - C) / π`` scaled by a power of two: every cost is a sum of
  nonnegative terms, so rounding errs by at most a *relative* ``γ`` of each cost (``_Fast``);
* argmax and the gap to the runner-up in integer reductions: nonnegative float32 values order
  like their int32 bit patterns, so the class index rides in the low bits (``_top``);
* pixels whose gap is within the rounding bound are re-decided by the reference.

Mixtures ``Σ_v w_kv C_v`` (K of them, ``w >= 0``) mix the V vertex cost maps in float32: the
cost is linear in ``C`` and the vertices' shifts differ from the mixture's by a column constant.
Where every vertex picks the same class with a certified margin, so does every mixture; elsewhere
only classes that no vertex winner beats in every vertex are mixed, and near ties are re-decided
by the reference on the mixed matrix (``mix_costs``), so the result equals ``decide`` on it.
"""

from __future__ import annotations

import math
from collections.abc import Iterator

import torch

from costseg.costs import mix_costs, symmetric_cost

CPU_CHUNK = 32768  # pixels per chunk on the CPU: (V·N x chunk) float32 costs stay in cache
GPU_CHUNK = 1 << 21  # one 1024 x 2048 image
U32, U64 = 2.0**-24, 2.0**-53  # unit roundoffs
INT_MAX, INF = 0x7FFFFFFF, 0x7F800000  # INF: bit pattern of float32 +inf (NaN lies above)
SMALL = (127 - 60) << 23  # bit pattern of 2**-60: below it, underflow voids relative bounds
TINY = 2.0**-120  # absolute slack (underflow of N products: N · 2**-149) for the pruning


def decide(
    probs: torch.Tensor,
    cost: torch.Tensor | None = None,
    priors: torch.Tensor | None = None,
) -> torch.Tensor:
    """Cost-based decision for every pixel, equal to the float64 reference on every pixel.

    Args:
        probs: (B, N, H, W) class probabilities >= 0 (float16/bfloat16/32/64, any device).
        cost: (N, N) cost matrix, rows = predicted class, columns = true class; ``None`` means the
            symmetric matrix (argmax, or maximum likelihood when priors are given).
        priors: ``None``, (N,) global or (N, H, W) pixel-wise priors π > 0: the rule is applied to
            ``p / π`` (a per-pixel column scaling).

    Returns:
        (B, H, W) int64 class indices.

    >>> p = torch.tensor([0.5, 0.3, 0.2]).view(1, 3, 1, 1)
    >>> C = torch.tensor([[0.0, 10, 1], [1, 0, 1], [1, 1, 0]])
    >>> decide(p, None).item(), decide(p, C).item()
    (0, 1)
    """
    n = _check(probs)
    cost = symmetric_cost(n) if cost is None else cost
    if cost.shape != (n, n):
        raise ValueError(f"cost matrix must be {n}x{n} for {n} classes, got {tuple(cost.shape)}")
    cost = cost.to(device=probs.device, dtype=torch.float64)[None]
    shifted = _shift(cost)
    fast = _Fast(cost, probs, priors, eps=(n + 4) * U64)  # eps: the reference's rounding
    b, _, h, w = probs.shape
    out = torch.empty(b, h * w, dtype=torch.long, device=probs.device)
    for i in range(b):
        redo, q64 = [], []
        for s, q in fast.chunks(i):
            labels = out[i, s : s + q.shape[1]]
            costs = fast.costs(q)[0]
            _, ambiguous = _top(costs, fast.gamma, fast.eps, fast.code, fast.low, True, labels)
            redo.append(ambiguous.nonzero()[:, 0] + s)
            q64.append(fast.exact_q(i, redo[-1]))  # while the chunk is in cache
        redo = torch.cat(redo)
        if len(redo):
            out[i, redo] = fast.settle(torch.cat(q64), shifted)
    return out.view(b, h, w)


def decide_mixtures(
    probs: torch.Tensor,
    vertices: torch.Tensor,
    weights: torch.Tensor,
    priors: torch.Tensor | None = None,
) -> torch.Tensor:
    """Decisions for K mixtures ``Σ_v w_kv C_v`` of V vertex matrices, in one pass.

    Equals ``decide(probs, mix_costs(vertices, weights)[k], priors)`` exactly for every k, at the
    cost of V vertex cost maps plus a cheap mixing step, instead of K full evaluations.

    Args:
        probs: (B, N, H, W) class probabilities >= 0.
        vertices: (V, N, N) cost matrices.
        weights: (K, V) mixture weights >= 0, each row with a positive entry
            (e.g. :func:`costseg.costs.barycentric_grid`).
        priors: as in :func:`decide`.

    Returns:
        (B, K, H, W) class indices, uint8 when N <= 256 (K label maps are large), else int64.

    >>> from costseg.costs import barycentric_grid, load_cost
    >>> V = torch.stack([load_cost(n) for n in ("robotistic", "altruistic", "egoistic")])
    >>> decide_mixtures(torch.rand(2, 19, 4, 5).softmax(1), V, barycentric_grid(0.1)).shape
    torch.Size([2, 66, 4, 5])
    """
    n = _check(probs)
    if vertices.shape[1:] != (n, n) or weights.ndim != 2 or weights.shape[1] != len(vertices):
        raise ValueError(
            f"expected vertices ({n} x {n} matrices) and weights (K, V), got "
            f"{tuple(vertices.shape)} and {tuple(weights.shape)}"
        )
    if not bool((weights >= 0).all() and (weights > 0).any(1).all()):
        raise ValueError("mixture weights must be >= 0 with a positive entry in each row")
    mixed = _shift(mix_costs(vertices, weights).to(probs.device))  # the reference matrices
    k = weights.shape[0]
    # eps: the reference's rounding on a mixed matrix (also the mixing in mix_costs), per T.
    fast = _Fast(vertices.to(probs.device, torch.float64), probs, priors, (n + 8) * U64)
    weights = weights.to(probs.device, torch.float64)
    mix = _Mixer(weights.float(), fast)
    b, _, h, w = probs.shape
    dtype = torch.uint8 if n <= 256 else torch.long  # K label maps add up
    out = torch.empty(b, k, h * w, dtype=dtype, device=probs.device)
    for i, (s, q) in ((j, c) for j in range(b) for c in fast.chunks(j)):
        costs = fast.costs(q)
        winner, ambiguous = _top(costs, fast.gamma, fast.eps, fast.code, fast.low)
        contested = ((winner != winner[:1]).any(0) | ambiguous.any(0)).nonzero()[:, 0]
        labels = out[i, :, s : s + q.shape[1]]
        if not len(contested):
            labels.copy_(winner[:1].expand(k, -1))
            continue
        picked = costs.view(-1, costs.shape[2]).index_select(1, contested)  # fast on 2-D views
        # Labels of pixel p will sit in column source[p] of table = [winner-0 labels, mixed]:
        # a gather, much faster than scattering K labels per contested pixel.
        table = torch.empty(k, len(winner[0]) + len(contested), dtype=dtype, device=probs.device)
        table[:, : len(winner[0])] = winner[:1]
        order, grid, column = mix(picked.view(*costs.shape[:2], -1), winner[:, contested], table)
        if len(grid):
            pixels, inverse = torch.unique(contested[order[column]], return_inverse=True)
            q64 = fast.exact_q(i, s + pixels)
            table[grid, len(winner[0]) + column] = fast.settle(
                q64, mixed, grid, weights, inverse
            ).to(dtype)
        source = torch.arange(len(winner[0]), device=probs.device)
        source[contested[order]] = len(source) + torch.arange(len(order), device=probs.device)
        torch.gather(table, 1, source.expand(k, -1), out=labels)
    return out.view(b, k, h, w)


class _Fast:
    """Float32 costs of V matrices for one call, with their certified rounding bound.

    ``costs(q)``: (V, N + 1, P) = ``weight @ q`` for (N, P) float32 ``q``. Rows ``:N`` use
    ``W = (C - C.min(0)) / π >= 0`` (global priors folded into the columns; argmin), row N is
    ``T = Σ_k R_k q_k`` with ``R = (C.max(0) - C.min(0) + |C|.max(0)) / π``, which bounds the
    magnitude of every reference cost. All terms are nonnegative, so each result errs by at most
    ``γ`` times its own value (plus underflow, below ``2**-149`` per term), and the reference by
    at most ``eps · T``. ``γ`` counts: ``ρ``, the measured rounding of the matrix to float32 (a
    power-of-2 scale keeps it in range); two roundings of the inputs where matmuls may use
    TF32/bfloat16; three roundings of q (casts, the division by pixel-wise priors); and
    ``γ_N = Nu / (1 - Nu)`` of a dot product of length N in any order.
    """

    def __init__(self, matrices: torch.Tensor, probs: torch.Tensor, priors, eps: float) -> None:
        b, n, h, w = probs.shape
        self.probs, self.priors = probs.reshape(b, n, h * w), _priors(priors, n, h, w, probs)
        low, high = matrices.amin(-2, keepdim=True), matrices.amax(-2, keepdim=True)
        weight = torch.cat([matrices - low, high - low + matrices.abs().amax(-2, True)], -2)
        self.weight64 = weight.reshape(-1, n)  # for q = p / π in float64
        if self.priors is not None and self.priors.ndim == 1:
            weight = weight / self.priors.double()
        top = weight.max().item()
        if top > 0:
            weight = weight * 2.0 ** -math.frexp(top)[1]  # exact
        single = weight.float()
        rho = ((single.double() - weight).abs() / weight).nan_to_num(0).max().item() + 4 * U64
        precision = torch.get_float32_matmul_precision()
        if probs.device.type == "cuda" and torch.backends.cuda.matmul.allow_tf32:
            precision = "high" if precision == "highest" else precision
        self.u_in = {"highest": 0.0, "high": 2.0**-11, "medium": 2.0**-8}[precision]
        dot = n * U32 / (1 - n * U32)
        self.gamma = (1 + rho) * (1 + self.u_in) ** 2 * (1 + U32) ** 3 * (1 + dot) - 1
        # float64: two roundings of the matrix (minus C.min, over π), one of q, the dot product.
        self.gamma64 = (1 + U64) ** 3 * (1 + n * U64 / (1 - n * U64)) - 1
        self.eps, self.rows = eps, single.shape[:2]
        self.weight = single.reshape(-1, n)
        self.code = torch.arange(n, dtype=torch.int32, device=probs.device).view(n, 1)
        self.low = (1 << max(1, (n - 1).bit_length())) - 1  # index bits in _top
        self.pixel_priors = (
            self.priors if self.priors is not None and self.priors.ndim == 2 else None
        )

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

    def chunks(self, image: int) -> Iterator[tuple[int, torch.Tensor]]:
        """(first pixel, (N, P) float32 q) for every chunk of pixels of one image."""
        probs = self.probs[image]
        step = CPU_CHUNK if probs.device.type == "cpu" else GPU_CHUNK
        for s in range(0, probs.shape[1], step):
            q = probs[:, s : s + step]
            if self.pixel_priors is not None:
                q = q.float() / self.pixel_priors[:, s : s + step].float()
            yield s, q.float()

    def settle(self, q: torch.Tensor, shifted: torch.Tensor, grid=None, weights=None, inverse=None):
        """Labels (R,) where float32 left it open: the same certificate in float64 (matmuls),
        then the reference where even that fails.

        Args:
            q: (U, N) float64 ``p / π`` of the pixels (:meth:`exact_q`).
            shifted: (1, N, N) the reference's shifted matrix, or (K, N, N) with ``grid``.
            grid: None or (R,) the mixture of each label; weights: (K, V) float64 mixture weights.
            inverse: None (R = U) or (R,) the pixel of each label.
        """
        costs = (q @ self.weight64.t()).view(len(q), *self.rows)
        if inverse is not None:
            q, costs = q[inverse], costs[inverse]
        gamma = self.gamma64
        if grid is None:
            costs = costs[:, 0]
        else:  # V more nonnegative terms
            costs = (weights[grid, :, None] * costs).sum(1)
            gamma = (1 + gamma) * (1 + len(weights[0]) * U64 / (1 - len(weights[0]) * U64)) - 1
        labels, unsure = _top64(costs, gamma, self.eps)
        unsure = unsure.nonzero()[:, 0]
        if len(unsure):
            matrices = shifted if grid is None else shifted[grid[unsure]]
            labels[unsure] = _reference(q[unsure], matrices)
        return labels


class _Mixer:
    """Certified decisions of K mixtures on contested pixels (see the module docstring)."""

    def __init__(self, weights: torch.Tensor, fast: _Fast) -> None:
        self.weights, self.fast, v = weights, fast, weights.shape[1]
        # A mixed cost (and T) sums V nonnegative terms: fast.gamma, the rounding of w to
        # float32, the matmul's inputs and a dot product of length V.
        dot = v * U32 / (1 - v * U32)
        self.gamma = (1 + fast.gamma) * (1 + U32) * (1 + fast.u_in) ** 2 * (1 + dot) - 1
        # Mixed signed differences (_pair): g for the costs, h for V + 4 roundings and the inputs.
        g = fast.gamma / (1 - fast.gamma)
        h = (1 + U32) ** (v + 4) * (1 + fast.u_in) ** 2 - 1
        self.slack = (1.25 * (g + 2 * h), 2.5 * fast.eps * (1 + g))

    def __call__(self, costs: torch.Tensor, winner: torch.Tensor, table: torch.Tensor):
        """Vertex costs (V, N + 1, P) and winners (V, P) of the contested pixels.

        Writes the labels into the last P columns of ``table`` (K, ·), the pixels grouped by
        their number of candidates. Returns that order (P,) and the (mixture, column) pairs to
        re-check.
        """
        candidate = self._candidates(costs, winner.long())
        count = candidate.sum(0)
        (k, v), n, p = self.weights.shape, costs.shape[1] - 1, costs.shape[2]
        order, redo, start = [], [], table.shape[1] - p
        for m in count.unique().tolist():
            sel = (count == m).nonzero()[:, 0]
            classes = candidate.index_select(1, sel).t().nonzero()[:, 1].view(-1, m).t()
            columns = table[:, start : start + len(sel)]
            if m == 1:
                columns.copy_(classes.expand(k, -1))
            else:
                rows = torch.cat([classes, torch.full_like(classes[:1], n)])  # candidates, T
                picked = costs.view(v, -1).index_select(1, (rows * p + sel).flatten())
                method = self._pair if m == 2 else self._many
                labels, unsure = method(picked.view(v, m + 1, -1), classes)
                columns.copy_(labels)
                grid, column = unsure.nonzero().unbind(1)
                redo.append(torch.stack([grid, column + start - (table.shape[1] - p)]))
            order.append(sel)
            start += len(sel)
        redo = torch.cat(redo, 1) if redo else costs.new_zeros(2, 0, dtype=torch.long)
        return torch.cat(order), redo[0], redo[1]

    def _many(self, picked: torch.Tensor, classes: torch.Tensor):
        """(V, m + 1, P) candidate costs and T, (m, P) classes → labels (K, P), re-check (K, P)."""
        k, v = self.weights.shape
        mixed = (self.weights @ picked.view(v, -1)).view(k, len(picked[0]), -1)
        code = classes.int()  # the class itself rides in the low bits
        return _top(mixed, self.gamma, self.fast.eps, code, self.fast.low, True)

    def _pair(self, picked: torch.Tensor, classes: torch.Tensor):
        """``_many`` for two candidates a < b: signs of the mixed difference ``x_b - x_a``.

        ``lo = w · (d - s)`` and ``-hi = -w · (d + s)`` with ``d = x_b - x_a`` and the slack ``s``
        covering the rounding of x (relative to ``x_a + x_b``), of these float32 operations and
        the reference's (``eps T``): ``lo > 0`` certifies a, ``-hi > 0`` certifies b.
        """
        (k, v), (a, b, total) = self.weights.shape, picked.unbind(1)
        slack = torch.add((a + b).mul_(self.slack[0]), total, alpha=self.slack[1]).add_(TINY)
        d = b - a
        rows = torch.stack([d - slack, (d + slack).neg_()], 1)
        lo, nhi = (self.weights @ rows.view(v, -1)).view(k, 2, -1).unbind(1)
        certain = torch.maximum(lo, nhi) > 0  # NaN: not certain
        # b where -hi > 0 (bit pattern >= 1: positive; -0.0 is INT_MIN), else a.
        pick_b = nhi.view(torch.int32).clamp(0, 1)
        first, second = classes.int().unbind(0)
        return pick_b.mul_(second - first).add_(first), ~certain

    def _candidates(self, costs: torch.Tensor, winner: torch.Tensor) -> torch.Tensor:
        """(N, P) bool: classes that no vertex winner beats in every vertex by a certain margin.

        A class beaten by the same class in every vertex is beaten at every mixture (w >= 0),
        in the reference too, so it can never be the decision. "Certain": ``x_j - x_a`` exceeds
        twice the rounding of both and of the reference (``_top``'s bounds, doubled).
        """
        costs, total = costs[:, :-1], costs[:, -1:]
        slack = 2 * self.fast.gamma / (1 - self.fast.gamma) * 1.01
        extra = total * (4 * self.fast.eps) + TINY
        beaten = None  # max over winners u of min over vertices of x_j - threshold_u (> 0: beaten)
        for best in winner:
            chosen = costs.gather(1, best.expand(costs.shape[0], 1, -1))
            threshold = (chosen * (1 + slack) + extra) / (1 - slack)
            margin = (costs - threshold).amin(0)
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
    """Argmin over dim -2 of float32 costs >= 0 whose last row is T, and where it is uncertain.

    With computed costs x, exact y, ``|x - y| <= γ y`` and the reference within ``eps · T`` of
    y (up to a per-pixel constant), the runner-up b and the argmin a satisfy
    ``y_b - y_a > 2 eps T`` -- the reference then decides a, uniquely -- when
    ``x_b - x_a > Δ x_b`` with ``Δ = 2.5γ / (1 - γ)`` (2γ for both roundings, γ/2 left for the
    reference's), ``x_b >= 10 eps T / γ`` and ``x_b >= 2**-60`` (underflow then negligible).

    Nonnegative floats order like their int32 bit patterns, whose low bits (``low``, a mask)
    carry ``code``, (m, P) or (m, 1) int32 labels of the rows (lowest wins ties); n ulps above a
    value lies at least ``n · 2**-24`` times it, and clearing the low bits moves a pattern by at
    most ``low``.

    Returns:
        (..., P) ``code`` of the argmin (int32, or written to ``out``) and (..., P) bool: not
        certified (also inf, NaN). With ``inplace``, ``costs`` is overwritten.
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
    """``_top`` for (R, m + 1) float64 costs (argmin over dim 1, last column T), in floats.

    Certified when ``y_b - y_a >= x_b - x_a - g (x_a + x_b) - (underflow)`` exceeds the
    reference's ``2 eps T (1 + g)``, ``g = γ / (1 - γ)``; 1.25 and ``1 - 4u`` absorb the
    rounding of the test itself.
    """
    if costs.shape[1] == 2:
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


def _check(probs: torch.Tensor) -> int:
    if probs.ndim != 4 or not probs.is_floating_point():
        raise ValueError(
            f"probs must be a float (B, N, H, W) tensor, got {probs.dtype} {tuple(probs.shape)}"
        )
    return probs.shape[1]


def _shift(costs: torch.Tensor) -> torch.Tensor:
    # Subtracting a per-column constant leaves every decision unchanged (see module docstring).
    return costs - costs.amax(dim=-2, keepdim=True)


def _priors(priors, n: int, h: int, w: int, probs: torch.Tensor) -> torch.Tensor | None:
    """None, (N,) or (N, H·W) priors on the probabilities' device, validated."""
    if priors is None:
        return None
    priors = torch.as_tensor(priors).to(probs.device)
    if not priors.is_floating_point():
        priors = priors.double()
    if priors.shape not in ((n,), (n, h, w)):
        raise ValueError(
            f"priors must be ({n},) or ({n}, {h}, {w}) for these probabilities, "
            f"got {tuple(priors.shape)}"
        )
    if not bool((priors > 0).all()):
        raise ValueError("priors must be > 0 everywhere (floor them, e.g. at 1e-5)")
    return priors.reshape(n, -1) if priors.ndim == 3 else priors
