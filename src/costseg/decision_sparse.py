"""Single-rule decisions on the CPU in one compiled pass (numba), from a sparse matrix.

A column constant changes no decision (:mod:`costseg.decision`), so with ``c_k`` the most
frequent entry of column k, ``C = 1 cᵀ + E`` decides as E: ``argmin_j e_j``, ``e_j = Σ_k E_jk
q_k``. E is sparse for the usual matrices (robotistic: ``-I``; the paper's others add the large
costs of missing a vulnerable class), so a pixel costs nnz(E) multiply-adds instead of N²,
summed four terms per pass over a block of pixels that stays in cache.

**Certificate.** The kernel sums ``L = E - g |E|``, rounded down to float32: its float32 sums
``l_j`` lie at or below ``e_j`` whatever their rounding (``g`` covers the row's depth of
rounding and q's three roundings), and within ``d M_j`` of it, ``M_j = Σ_k |E_jk| q_k``. The
smallest, ``l_a``, certifies the reference's decision a (float64; within ``eps T`` of exact,
``_Fast``'s T) when every other ``l_b`` exceeds ``l_a + d M_a + 2 eps T``: first with
``M_a <= r_a Σ_k q_k`` (``r_a``: the row's largest magnitude), vectorised; where that fails,
with ``M_a`` itself. A NaN or infinite q makes ``Σ_k q_k`` NaN or infinite: never certified.
The pixels left open go to ``_Fast.settle`` (float64 certificate, then the reference). As in the
whole decision layer, probabilities are >= 0.
"""

from __future__ import annotations

import math

import numba
import numpy as np
import torch

from costseg.decision_certified import TINY, U32, U64, _Fast
from costseg.decision_numba import _in_pieces

BLOCK = 512  # pixels decided together: (N x BLOCK) float32 probabilities stay in cache
CHUNK = 1 << 20  # pixels converted to float32 q at once (other types, pixel-wise priors)
ROUNDING = 1 + 2.0**-20  # rounds the float64 bound's coefficients up past their float32 casts


# fastmath "contract" only: multiply-adds fused (one rounding less), NaN and inf kept.
JIT = dict(nogil=True, cache=True, boundscheck=False, error_model="numpy", fastmath={"contract"})


@numba.njit(**JIT)
def _sum_groups(q, s, cols, vals, first, last, out):
    """``out = Σ_t vals[t] q[cols[t], s : s + BLOCK]`` for t in ``first:last``, four terms per
    pass (loads and stores, not arithmetic, bound a pass; the rounding bound holds in any order
    of summation)."""
    if first == last:
        out[:] = 0
    for t in range(first, last, 4):
        a, b, c, d = vals[t], vals[t + 1], vals[t + 2], vals[t + 3]
        row_a, row_b = q[cols[t], s : s + BLOCK], q[cols[t + 1], s : s + BLOCK]
        row_c, row_d = q[cols[t + 2], s : s + BLOCK], q[cols[t + 3], s : s + BLOCK]
        if t == first:
            for i in range(BLOCK):
                out[i] = (a * row_a[i] + b * row_b[i]) + (c * row_c[i] + d * row_d[i])
        else:
            for i in range(BLOCK):
                out[i] += (a * row_a[i] + b * row_b[i]) + (c * row_c[i] + d * row_d[i])


@numba.njit(**JIT)
def _decide_blocks(q, matrix, certificate, labels, start, stop):
    """Pixels ``start:stop`` (whole blocks) of (N, P) float32 q; returns those left open.

    Args:
        matrix: (indptr, cols, vals, sizes): the lower-bound matrix's entries (float32) row by
            row, padded with zeros to groups of four, and their magnitudes.
        certificate: (coef, size_coef, reference): per decided class, float32 coefficients of
            ``Σ_k q_k`` and of the row's magnitude M_a; that of ``Σ_k q_k`` for the reference's
            rounding alone.
        labels: (P,) int64 output.
    """
    indptr, cols, vals, sizes = matrix
    coef, size_coef, reference = certificate
    n, every = q.shape[0], -(-q.shape[0] // 4) * 4
    classes, ones = np.arange(every) % n, (np.arange(every) < n).astype(np.float32)
    cost, best = np.empty(BLOCK, np.float32), np.empty(BLOCK, np.float32)
    second, total = np.empty(BLOCK, np.float32), np.empty(BLOCK, np.float32)
    arg, flags = np.empty(BLOCK, np.int32), np.empty(BLOCK, np.uint8)
    opened, count = np.empty(1024, np.int64), 0
    for s in range(start, stop, BLOCK):
        _sum_groups(q, s, classes, ones, 0, every, total)
        best[:], second[:], arg[:] = np.inf, np.inf, 0
        for j in range(n):
            last = indptr[j + 1] - 4  # the last group joins the pass that keeps the best two
            _sum_groups(q, s, cols, vals, indptr[j], last, cost)
            a, b, c, d = vals[last], vals[last + 1], vals[last + 2], vals[last + 3]
            row_a, row_b = q[cols[last], s : s + BLOCK], q[cols[last + 1], s : s + BLOCK]
            row_c, row_d = q[cols[last + 2], s : s + BLOCK], q[cols[last + 3], s : s + BLOCK]
            label = np.int32(j)
            for i in range(BLOCK):  # branch-free, so that it vectorises; ties keep the lower j
                group = (a * row_a[i] + b * row_b[i]) + (c * row_c[i] + d * row_d[i])
                y, low, old = cost[i] + group, best[i], arg[i]
                second[i] = np.minimum(second[i], np.maximum(y, low))
                arg[i] = label if y < low else old
                best[i] = np.minimum(y, low)
        out = labels[s : s + BLOCK]
        for i in range(BLOCK):  # with M_a <= r_a Σ_k q_k: vectorised
            label, gap = arg[i], second[i] - best[i]
            sure = (gap > coef[label] * total[i] + np.float32(TINY)) & (gap < np.inf)
            out[i], flags[i] = label, np.uint8(1) - np.uint8(sure)
        for i in range(BLOCK):  # the rest with M_a itself
            gap = second[i] - best[i]
            if flags[i] and gap > 0 and gap < np.inf:
                size, label = np.float32(0), arg[i]
                for t in range(indptr[label], indptr[label + 1]):
                    size += sizes[t] * q[cols[t], s + i]
                need = size_coef[label] * size + reference * total[i] + np.float32(TINY)
                flags[i] = np.uint8(1) - np.uint8(gap > need)
            if flags[i]:
                if count == len(opened):  # full: twice as large
                    opened = np.concatenate((opened, np.empty(count, np.int64)))
                opened[count], count = s + i, count + 1
    return opened[:count].copy()


class SparseRule:
    """One matrix's sparse part E, float32, and its certificate, for :func:`_decide_blocks`.

    Args:
        fast: the matrix's ``_Fast`` (priors, T's coefficients and ``eps``; the open pixels'
            re-check).
        cost: (1, N, N) float64 cost matrix.
    """

    def __init__(self, fast: _Fast, cost: torch.Tensor) -> None:
        n = cost.shape[-1]
        sparse = cost[0] - cost[0].mode(0, keepdim=True).values
        total = fast.weight64[n].cpu()  # T's coefficients: R_k, bounding |reference cost| / q_k
        if fast.priors is not None and fast.priors.ndim == 1:  # global priors: into the columns
            sparse, total = sparse / fast.priors.cpu().double(), total / fast.priors.cpu().double()
        top = sparse.abs().max().item()
        scale = 2.0 ** -math.frexp(top)[1] if top > 0 else 1.0  # exact: keeps float32 in range
        sparse = sparse * scale
        magnitude, nonzero = sparse.abs(), sparse != 0
        # Row j's float32 sum: terms rounded at most depth_j times, q three times before.
        gamma = (1 + U32) ** 3 * (1 + _gamma(_depth(nonzero.sum(1)))) - 1
        margin = gamma * (1 + U32) * (1 + 8 * U64)  # 8 u64: the float64 steps before
        g = 1.01 * margin / (1 - margin)
        # Lower bounds of the costs: entries moved down by g |E|, then rounded down.
        single = _round_down(sparse - g[:, None] * magnitude)
        self.matrix = _padded_rows(single)
        # A row's lower bound lies within d M_a of its cost, M_a <= r_a Σ_k q_k.
        d = g + U32 * (1 + g) * (1 + 8 * U64) + gamma * (1 + g) * (1 + U32)
        reference = 2 * fast.eps * (total * scale).max().item()  # 2 eps T <= this Σ_k q_k
        shrink = (1 - U32) ** 3 * (1 - _gamma(_depth(torch.tensor(n))))  # computed Σ_k q_k
        up = (1 + U32) ** 2 / shrink * ROUNDING  # and the test's roundings, and the cast
        coef = ((d * magnitude.amax(1) + reference) * up).float().numpy()
        # M_a itself from |lower| >= (1 - g)(1 - u)|E|, summed one term after another.
        terms = torch.tensor(np.diff(self.matrix[0]))
        shrink_row = (1 - U32) ** 3 * (1 - _gamma(terms))
        size_coef = (d / ((1 - g) * (1 - U32)) * up * shrink / shrink_row).float().numpy()
        self.certificate = coef, size_coef, np.float32(reference * up)
        # Chunks: a float32 image without pixel-wise priors is read where it lies.
        as_is = fast.probs.dtype == torch.float32 and fast.pixel_priors is None
        self.step = fast.probs.shape[2] if as_is else CHUNK

    def chunk(self, q: torch.Tensor, labels: torch.Tensor) -> torch.Tensor:
        """(N, P) float32 q → (P,) int64 labels written into ``labels``; returns the open pixels."""
        q, n, p = q.contiguous().numpy(), q.shape[0], q.shape[1]
        whole, out, args = p - p % BLOCK, labels.numpy(), (self.matrix, self.certificate)
        opened = _in_pieces(_decide_blocks, (q, *args, out), whole, BLOCK)
        if whole < p:  # the last pixels, padded to a block
            tail = np.zeros((n, BLOCK), np.float32)
            tail[:, : p - whole] = q[:, whole:]
            tail_labels = np.empty(BLOCK, np.int64)
            tail_open = _decide_blocks(tail, *args, tail_labels, 0, BLOCK)
            out[whole:] = tail_labels[: p - whole]
            opened.append(tail_open[tail_open < p - whole] + whole)
        return torch.from_numpy(np.concatenate(opened))


def _round_down(values: torch.Tensor) -> torch.Tensor:
    """float64 → float32, each rounded down."""
    single = values.float()
    above = single.double() > values
    return torch.where(above, torch.nextafter(single, torch.tensor(-math.inf)), single)


def _depth(terms: torch.Tensor) -> torch.Tensor:
    """The most roundings a term of a sum of ``terms`` terms undergoes in ``_decide_blocks``:
    four in its group's pass (product, pair, pairs, accumulation), one in each later pass."""
    return (terms.clamp(min=1) + 3) // 4 + 3


def _padded_rows(matrix: torch.Tensor) -> tuple[np.ndarray, ...]:
    """(indptr, cols, vals, |vals|) of a float32 matrix's nonzero entries, row by row, each row
    padded with zero terms to a positive multiple of four (on one of its columns: a zero times
    a finite q adds nothing; a NaN or inf q opens the pixel anyway)."""
    indptr, cols, vals = [0], [], []
    for row in matrix:
        (where,) = row.nonzero(as_tuple=True)
        pad = -len(where) % 4 if len(where) else 4
        cols += where.tolist() + [where[0].item() if len(where) else 0] * pad
        vals += row[where].tolist() + [0.0] * pad
        indptr.append(len(cols))
    vals = np.array(vals, np.float32)
    return np.array(indptr), np.array(cols), vals, np.abs(vals)


def _gamma(m: torch.Tensor) -> torch.Tensor:
    """float64 ``γ_m = m u / (1 - m u)``: the relative error of m float32 roundings."""
    return m.double() * U32 / (1 - m.double() * U32)
