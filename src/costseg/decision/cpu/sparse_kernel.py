"""The compiled single-rule kernel (numba) behind :class:`.sparse_rule.SparseRule`: the grouped
sparse part of a matrix summed block by block of pixels in cache, the best two and their
certificate, the open pixels' q gathered; and the reference for those pixels, compiled."""

from __future__ import annotations

import numba
import numpy as np

from costseg.decision.certificate import TINY
from costseg.decision.cpu.block_steps import keep
from costseg.decision.cpu.row_groups import PASS, TOTAL

BLOCK = 1024  # pixels decided together: (N x BLOCK) float32 probabilities stay in cache


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
def reference_pixels(q, shifted_t, priors, labels, start, stop):
    """``reference.reference_labels``, compiled, for pixels ``start:stop`` of (R, N) float32 q
    (exactly p): ``p / π`` in float64, then each product and sum rounded once (no fastmath:
    called from Python, as numba compiles a callee with its caller's flags), ascending k; the
    first minimum. -1 where a cost is NaN (left to torch's reference). ``shifted_t``: (N, M) the
    transposed shifted matrix (M candidates: a defer row last)."""
    n, m = shifted_t.shape
    costs = np.empty(m, np.float64)
    for r in range(start, stop):
        costs[:] = 0.0
        for k in range(n):
            x = np.float64(q[r, k]) / priors[k]
            for j in range(m):
                costs[j] = costs[j] + shifted_t[k, j] * x
        best = 0
        for j in range(m):
            if costs[j] < costs[best]:
                best = j
        labels[r] = -1 if np.isnan(costs).any() else best


@numba.njit(**JIT)
def scratch(program):
    """The buffers of :func:`decide_block` for a program: ``work`` (its rows of
    sums, zeros first, +inf last), best, second (float32), arg, flags (int32), each of a block."""
    rows = program[4]
    work = np.zeros((rows, BLOCK), np.float32)
    work[rows - 1] = np.inf
    best, second = np.empty(BLOCK, np.float32), np.empty(BLOCK, np.float32)
    return work, best, second, np.empty(BLOCK, np.int32), np.empty(BLOCK, np.int32)


@numba.njit(**JIT)
def decide_block(q, s, program, certificate, buffers, out):
    """The block of pixels ``s : s + BLOCK`` of (N, P) float32 q: each pixel's row of the argmin
    written to ``out`` (BLOCK,), and ``flags`` of ``buffers`` (:func:`scratch`) set to 1 where it
    is left open (argument meanings: :func:`decide_blocks`)."""
    passes, cols, vals, results, _ = program
    coef, support, reference = certificate
    work, best, second, arg, flags = buffers
    total = work[TOTAL]
    for p in range(len(passes)):
        target, prefix, first, last = passes[p]
        _sums(q, s, cols, vals, first, last, work[prefix], work[target])
    _best_two(q, s, work, results, best, second, arg)
    for i in range(BLOCK):  # M_a <= r_a Σ_k q_k over a's support
        label, gap = arg[i], second[i] - best[i]
        need = coef[label] * work[support[label], i] + reference * total[i]
        sure = (gap > need + np.float32(TINY)) & (gap < np.inf)
        out[i], flags[i] = label, np.int32(1) - np.int32(sure)


@numba.njit(**JIT)
def decide_blocks(q, program, certificate, labels, start, stop):
    """Pixels ``start:stop`` (whole blocks) of (N, P) float32 q; returns those left open and
    their (R, N) q, gathered while in cache.

    Args:
        program: (passes, cols, vals, results, rows): each pass ``(out, prefix, first, stop)``
            writes ``work[out] = work[prefix] + Σ`` of terms ``first:stop`` (float32 ``cols``,
            ``vals``): Σ_k q_k, the supports' sums, the groups' shared sums, then the rows but
            their last term; ``results``: (prefix, col, val) of each candidate's cost (a class,
            or deferring), ``work[prefix] + val q[col]``, padded to a multiple of four with the
            +inf row; ``rows``: the buffer's row count.
        certificate: (coef, support, reference): per candidate, the float32 coefficient of
            ``Σ_k q_k`` over its support and that sum's row of ``work``; the coefficient of
            ``Σ_k q_k`` for the reference's rounding.
        labels: (P,) int64 output.
    """
    n = q.shape[0]
    buffers = scratch(program)
    flags, index = buffers[4], np.empty(BLOCK, np.int64)
    opened, count = np.empty(1024, np.int64), 0
    values = np.empty((1024, n), np.float32)
    for s in range(start, stop, BLOCK):
        decide_block(q, s, program, certificate, buffers, labels[s : s + BLOCK])
        unsure = 0
        for i in range(BLOCK):  # the pixels left open, gathered
            index[unsure] = i
            unsure += flags[i]
        opened, values = room(opened, values, count + unsure)
        for r in range(unsure):
            opened[count + r] = s + index[r]
            for k in range(n):
                values[count + r, k] = q[k, s + index[r]]
        count += unsure
    return opened[:count].copy(), values[:count].copy()


@numba.njit(**JIT)
def room(opened, values, needed):
    """``opened`` (R,) and ``values`` (R, N) grown (to twice, and a block more) when ``needed``
    rows do not fit."""
    if needed <= len(opened):
        return opened, values
    opened = np.concatenate((opened, np.empty(len(opened) + BLOCK, np.int64)))
    values = np.concatenate((values, np.empty((len(values) + BLOCK, values.shape[1]), np.float32)))
    return opened, values
