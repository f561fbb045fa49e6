"""Single-rule decisions on the CPU in one compiled pass (numba), from a sparse matrix.

A column constant changes no decision (:mod:`costseg.decision`), so with ``c_k`` the most
frequent entry of column k, ``C = 1 cᵀ + E`` decides as E: ``argmin_j e_j``, ``e_j = Σ_k E_jk
q_k``. E is sparse for the usual matrices (robotistic: ``-I``; the paper's others add the large
costs of missing a vulnerable class), and rows of the same kind share most entries (the
egoistic matrix's seven static classes differ only on the diagonal). So rows are grouped
(:func:`costseg.decision_groups.shared_rows`): a group's shared entries B are summed once per
pixel, each row adds its own rest ``D_j = E_j - B``. The sums run over a block of pixels that
stays in cache, up to four terms per pass; each row's last term joins the pass that keeps the
best two.

**Certificate.** The kernel sums ``L = B' + D'_j``, the entries moved down by ``g |.|`` and
rounded down to float32: its float32 sums ``l_j`` lie at or below ``e_j`` whatever their
rounding (``g`` covers the row's depth of rounding and q's three roundings), and within ``d M_j``
of it, ``M_j = Σ_k (|B_k| + |D_jk|) q_k``. The smallest, ``l_a``, certifies the reference's
decision a (float64; within ``eps T`` of exact, ``_Fast``'s T) when every other ``l_b`` exceeds
``l_a + d M_a + 2 eps T``, with ``M_a <= r_a Σ_k q_k`` over the columns of a's group (``r_a``:
the row's largest magnitude), vectorised. A NaN or infinite q makes ``Σ_k q_k`` NaN or infinite:
never certified. The pixels left open are decided by the float64 reference itself, on their q
gathered while in cache, where q is exactly p (no pixel-wise priors; float32 and narrower
types); else, and for NaN costs, they go to ``_Fast.settle``. As in the whole decision layer,
probabilities are >= 0.
"""

from __future__ import annotations

import math
from functools import lru_cache

import numba
import numpy as np
import torch

from costseg.decision_blocks import keep
from costseg.decision_certified import TINY, U32, U64, _Fast
from costseg.decision_groups import PASS, TOTAL, program, shared_rows, supports, with_zeros
from costseg.decision_numba import chunk_step
from costseg.threads import in_pieces

BLOCK = 1024  # pixels decided together: (N x BLOCK) float32 probabilities stay in cache
CHUNK = 1 << 20  # pixels converted to float32 q at once (other types, pixel-wise priors)
ROUNDING = 1 + 2.0**-20  # rounds the float64 bound's coefficients up past their float32 casts


# fastmath "contract" only: multiply-adds fused (one rounding less), NaN and inf kept.
JIT = dict(nogil=True, cache=True, boundscheck=False, error_model="numpy", fastmath={"contract"})


@numba.njit(**JIT)
def _sums(q, s, cols, vals, first, stop, prefix, out):
    """``out = prefix + Σ_t vals[t] q[cols[t], s : s + BLOCK]`` for t in ``first:stop``, up to
    four terms per pass (loads and stores, not arithmetic, bound a pass). Each term is rounded
    at most four times in its pass and once in each later one. ``prefix`` is another row than
    ``out``: loops on two rows that might overlap would not vectorise."""
    for t in range(first, stop, PASS):
        count, last = min(PASS, stop - t), stop - 1
        tb, tc, td = min(t + 1, last), min(t + 2, last), min(t + 3, last)
        a, b, c, d = vals[t], vals[tb], vals[tc], vals[td]
        row_a, row_b = q[cols[t], s : s + BLOCK], q[cols[tb], s : s + BLOCK]
        row_c, row_d = q[cols[tc], s : s + BLOCK], q[cols[td], s : s + BLOCK]
        if t == first:
            if count == 4:
                for i in range(BLOCK):
                    pair = a * row_a[i] + b * row_b[i]
                    out[i] = prefix[i] + (pair + (c * row_c[i] + d * row_d[i]))
            elif count == 3:
                for i in range(BLOCK):
                    out[i] = prefix[i] + ((a * row_a[i] + b * row_b[i]) + c * row_c[i])
            elif count == 2:
                for i in range(BLOCK):
                    out[i] = prefix[i] + (a * row_a[i] + b * row_b[i])
            else:
                for i in range(BLOCK):
                    out[i] = prefix[i] + a * row_a[i]
        elif count == 4:
            for i in range(BLOCK):
                out[i] += (a * row_a[i] + b * row_b[i]) + (c * row_c[i] + d * row_d[i])
        elif count == 3:
            for i in range(BLOCK):
                out[i] += (a * row_a[i] + b * row_b[i]) + c * row_c[i]
        elif count == 2:
            for i in range(BLOCK):
                out[i] += a * row_a[i] + b * row_b[i]
        else:
            for i in range(BLOCK):
                out[i] += a * row_a[i]


@numba.njit(**JIT)
def _best_two(q, s, work, rows, best, second, arg):
    """Smallest and second smallest of the costs ``work[prefix] + val q[col, s : s + BLOCK]``
    for ``rows = (prefix, col, val)`` (a multiple of four; ties keep the first), four per pass.
    Plain selects, which compile to min and max instructions: NaN costs are skipped, but a
    pixel with any (from a NaN or infinite q) has a non-finite ``Σ_k q_k`` and is never
    certified."""
    prefix, cols, vals = rows
    best[:], second[:], arg[:] = np.inf, np.inf, 0
    for j in range(0, len(prefix), 4):
        row_a, row_b = work[prefix[j]], work[prefix[j + 1]]
        row_c, row_d = work[prefix[j + 2]], work[prefix[j + 3]]
        q_a, q_b = q[cols[j], s : s + BLOCK], q[cols[j + 1], s : s + BLOCK]
        q_c, q_d = q[cols[j + 2], s : s + BLOCK], q[cols[j + 3], s : s + BLOCK]
        a, b, c, d = vals[j], vals[j + 1], vals[j + 2], vals[j + 3]
        for i in range(BLOCK):
            low, high, label = best[i], second[i], arg[i]
            low, high, label = keep(row_a[i] + a * q_a[i], np.int32(j), low, high, label)
            low, high, label = keep(row_b[i] + b * q_b[i], np.int32(j + 1), low, high, label)
            low, high, label = keep(row_c[i] + c * q_c[i], np.int32(j + 2), low, high, label)
            low, high, label = keep(row_d[i] + d * q_d[i], np.int32(j + 3), low, high, label)
            best[i], second[i], arg[i] = low, high, label


@numba.njit(nogil=True, cache=True, boundscheck=False, error_model="numpy")
def _reference_pixels(q, shifted_t, priors, labels, start, stop):
    """``_reference`` for pixels ``start:stop`` of (R, N) float32 q (exactly p): ``p / π`` in
    float64, then each product and sum rounded once (no fastmath: called from Python, as numba
    compiles a callee with its caller's flags), ascending k; the first minimum. -1 where a cost
    is NaN (left to torch's reference)."""
    n = q.shape[1]
    costs = np.empty(n, np.float64)
    for r in range(start, stop):
        costs[:] = 0.0
        for k in range(n):
            x = np.float64(q[r, k]) / priors[k]
            for j in range(n):
                costs[j] = costs[j] + shifted_t[k, j] * x
        best = 0
        for j in range(n):
            if costs[j] < costs[best]:
                best = j
        labels[r] = -1 if np.isnan(costs).any() else best


@numba.njit(**JIT)
def _decide_blocks(q, program, certificate, labels, start, stop):
    """Pixels ``start:stop`` (whole blocks) of (N, P) float32 q; returns those left open and
    their (R, N) q, gathered while in cache.

    Args:
        program: (passes, cols, vals, results, rows): each pass ``(out, prefix, first, stop)``
            writes ``work[out] = work[prefix] + Σ`` of terms ``first:stop`` (float32 ``cols``,
            ``vals``): Σ_k q_k, the supports' sums, the groups' shared sums, then the rows but
            their last term; ``results``: (prefix, col, val) of each class's cost, ``work[prefix]
            + val q[col]``, padded to a multiple of four with the +inf row; ``rows``: the
            buffer's row count.
        certificate: (coef, support, reference): per decided class, the float32 coefficient
            of ``Σ_k q_k`` over its support and that sum's row of ``work``; the coefficient of
            ``Σ_k q_k`` for the reference's rounding.
        labels: (P,) int64 output.
    """
    passes, cols, vals, results, rows = program
    coef, support, reference = certificate
    n = q.shape[0]
    work = np.zeros((rows, BLOCK), np.float32)
    work[rows - 1] = np.inf
    best, second = np.empty(BLOCK, np.float32), np.empty(BLOCK, np.float32)
    arg, flags = np.empty(BLOCK, np.int32), np.empty(BLOCK, np.int32)
    index = np.empty(BLOCK, np.int64)
    opened, count = np.empty(1024, np.int64), 0
    values, total = np.empty((1024, n), np.float32), work[TOTAL]
    for s in range(start, stop, BLOCK):
        for p in range(len(passes)):
            out, prefix, first, last = passes[p]
            _sums(q, s, cols, vals, first, last, work[prefix], work[out])
        _best_two(q, s, work, results, best, second, arg)
        out = labels[s : s + BLOCK]
        for i in range(BLOCK):  # M_a <= r_a Σ_k q_k over a's support
            label, gap = arg[i], second[i] - best[i]
            need = coef[label] * work[support[label], i] + reference * total[i]
            sure = (gap > need + np.float32(TINY)) & (gap < np.inf)
            out[i], flags[i] = label, np.int32(1) - np.int32(sure)
        unsure = 0
        for i in range(BLOCK):  # the pixels left open, gathered
            index[unsure] = i
            unsure += flags[i]
        if count + unsure > len(opened):  # full: twice as large
            opened = np.concatenate((opened, np.empty(len(opened) + BLOCK, np.int64)))
            values = np.concatenate((values, np.empty((len(values) + BLOCK, n), np.float32)))
        for r in range(unsure):
            opened[count + r] = s + index[r]
            for k in range(n):
                values[count + r, k] = q[k, s + index[r]]
        count += unsure
    return opened[:count].copy(), values[:count].copy()


class SparseRule:
    """One matrix's grouped sparse part, float32, and its certificate, for :func:`_decide_blocks`.

    Args:
        fast: the matrix's ``_Fast`` (priors, T's coefficients and ``eps``; the open pixels'
            re-check).
        cost: (1, N, N) float64 cost matrix; shifted: (1, N, N) the reference's.
    """

    def __init__(self, fast: _Fast, cost: torch.Tensor, shifted: torch.Tensor) -> None:
        n = cost.shape[-1]
        total = fast.weight64[n].cpu()  # T's coefficients: R_k, bounding |reference cost| / q_k
        folded = fast.priors is not None and fast.priors.ndim == 1  # global priors: in E
        priors = fast.priors.cpu().double() if folded else torch.ones(n, dtype=torch.float64)
        matrices = (cost[0], total, priors)
        self.program, self.certificate = _prepared(
            *(x.numpy().tobytes() for x in matrices), fast.eps
        )
        # Open pixels: the reference here where q is exactly p (no pixel-wise priors; float32
        # and narrower types), else _Fast.settle.
        self.reference64 = None
        if fast.pixel_priors is None and fast.probs.dtype != torch.float64:
            self.reference64 = shifted[0].cpu().t().contiguous().numpy(), priors.numpy()
        self.step = chunk_step(fast, CHUNK)

    def chunk(self, q: torch.Tensor, labels: torch.Tensor) -> torch.Tensor:
        """(N, P) float32 q → (P,) int64 labels written into ``labels``; returns the pixels left
        to ``_Fast.settle``: those open where q is not exactly p, else those with NaN costs."""
        q, n, p = q.contiguous().numpy(), q.shape[0], q.shape[1]
        whole, out, args = p - p % BLOCK, labels.numpy(), (self.program, self.certificate)
        pieces = in_pieces(_decide_blocks, (q, *args, out), whole, BLOCK)
        if whole < p:  # the last pixels, padded to a block
            tail = np.zeros((n, BLOCK), np.float32)
            tail[:, : p - whole] = q[:, whole:]
            tail_labels = np.empty(BLOCK, np.int64)
            opened, values = _decide_blocks(tail, *args, tail_labels, 0, BLOCK)
            out[whole:] = tail_labels[: p - whole]
            pieces.append((opened[opened < p - whole] + whole, values[opened < p - whole]))
        opened = np.concatenate([part[0] for part in pieces])
        values = np.concatenate([part[1] for part in pieces])
        if self.reference64 is not None and len(opened):  # the reference, on these q
            decided = np.empty(len(opened), np.int64)
            in_pieces(_reference_pixels, (values, *self.reference64, decided), len(opened))
            out[opened] = decided
            opened = opened[decided < 0]
        return torch.from_numpy(opened)


@lru_cache(maxsize=32)
def _prepared(cost: bytes, total: bytes, priors: bytes, eps: float) -> tuple:
    """The kernel's program and certificate for a float64 (N, N) matrix, T's (N,) coefficients
    and (N,) global priors (ones where none), cached: the same matrix comes image after image."""
    total, priors = (torch.from_numpy(np.frombuffer(x).copy()) for x in (total, priors))
    n = len(total)
    cost = torch.from_numpy(np.frombuffer(cost).copy()).view(n, n)
    sparse = cost - cost.mode(0, keepdim=True).values
    sparse, total = sparse / priors, total / priors  # global priors: into the columns
    top = sparse.abs().max().item()
    scale = 2.0 ** -math.frexp(top)[1] if top > 0 else 1.0  # exact: keeps float32 in range
    sparse = sparse * scale
    group, shared = shared_rows(sparse.numpy())
    group, shared = torch.from_numpy(group), torch.from_numpy(shared)
    base = with_zeros(shared)[group]  # (N, N): each row's B (group -1: the zero row)
    own = sparse - base  # D; B + D = E within u64 |D|, far inside g's 1 % slack
    magnitude = base.abs() + own.abs()
    terms = (own != 0).sum(1)  # the last one in the pass that keeps the best two
    steps = with_zeros(_passes((shared != 0).sum(1)))[group] + _passes(terms - 1) + (terms > 0)
    # Row j's float32 sum: terms rounded at most passes + 3 times, q three times before.
    gamma = (1 + U32) ** 3 * (1 + _gamma(steps + 3)) - 1
    margin = gamma * (1 + U32) * (1 + 8 * U64)  # 8 u64: the float64 steps before
    g, g_shared = 1.01 * margin / (1 - margin), torch.zeros(len(shared), dtype=torch.float64)
    for index in range(len(shared)):  # a group's shared sum: one g for its rows
        members = group == index
        g[members] = g_shared[index] = g[members].max()
    # Lower bounds of the costs: entries moved down by g |.|, then rounded down.
    shared = _round_down(shared - g_shared[:, None] * shared.abs())
    own = _round_down(own - g[:, None] * own.abs())
    sums, support = supports(magnitude, group)
    plan = program(sums, shared, own, group.numpy())
    # A row's lower bound lies within d M_a of its cost, M_a <= r_a Σ_k q_k over its
    # group's support.
    d = g + U32 * (1 + g) * (1 + 8 * U64) + gamma * (1 + g) * (1 + U32)
    reference = 2 * eps * (total * scale).max().item()  # 2 eps T <= this Σ_k q_k
    shrink = (1 - U32) ** 3 * (1 - _gamma(_passes(torch.tensor(n)) + 3))  # computed Σ_k q_k
    up = (1 + U32) ** 3 / shrink * ROUNDING  # and the test's roundings, and the cast
    coef = (d * magnitude.amax(1) * up).float().numpy()  # of the support's Σ_k q_k
    return plan, (coef, support, np.float32(reference * up))


def _round_down(values: torch.Tensor) -> torch.Tensor:
    """float64 → float32 (as float64), each rounded down."""
    single = values.float()
    above = single.double() > values
    return torch.where(above, torch.nextafter(single, torch.tensor(-math.inf)), single).double()


def _passes(terms: torch.Tensor) -> torch.Tensor:
    """Passes of up to four terms for sums of ``terms`` terms."""
    return (terms + PASS - 1) // PASS


def _gamma(m: torch.Tensor) -> torch.Tensor:
    """float64 ``γ_m = m u / (1 - m u)``: the relative error of m float32 roundings."""
    return m.double() * U32 / (1 - m.double() * U32)
