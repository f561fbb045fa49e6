"""The compiled single-rule kernel (numba) behind :class:`.sparse_rule.SparseRule`: the grouped
sparse part of a matrix summed block by block of pixels in cache, the best two and their
certificate, the open pixels' q gathered; and the reference for those pixels, compiled. A
regional value system (docs/definitions.md §21) decides runs of pixels of one matrix each
(:func:`decide_runs`): a block is then a run's piece, at most ``BLOCK`` pixels."""

from __future__ import annotations

import numba
import numpy as np

from costseg.decision.certificate import TINY
from costseg.decision.cpu.block_steps import keep
from costseg.decision.cpu.row_groups import PASS, TOTAL

BLOCK = 1024  # pixels decided together: (N x BLOCK) float32 probabilities stay in cache
VECTOR = 16  # float32 lanes of an AVX-512 vector (a cache line): where a run's loads start
LOOP = 64  # pixels of one iteration of the vectorised loops (4 vectors): a run's size rounds up


# fastmath "contract" only: multiply-adds fused (one rounding less), NaN and inf kept.
JIT = dict(nogil=True, cache=True, boundscheck=False, error_model="numpy", fastmath={"contract"})


@numba.njit(**JIT)
def _sums(q, s, size, cols, vals, first, stop, prefix, out):
    """``out = prefix + Σ_t vals[t] q[cols[t], s : s + size]`` for t in ``first:stop``, up to
    four terms per pass (loads and stores, not arithmetic, bound a pass). Each term is rounded
    at most four times in its pass and once in each later one. ``prefix`` is another row than
    ``out``: loops on two rows that might overlap would not vectorise."""
    for t in range(first, stop, PASS):
        count, last = min(PASS, stop - t), stop - 1
        tb, tc, td = min(t + 1, last), min(t + 2, last), min(t + 3, last)
        a, b, c, d = vals[t], vals[tb], vals[tc], vals[td]
        row_a, row_b = q[cols[t], s : s + size], q[cols[tb], s : s + size]
        row_c, row_d = q[cols[tc], s : s + size], q[cols[td], s : s + size]
        if t == first:
            if count == 4:
                for i in range(size):
                    pair = a * row_a[i] + b * row_b[i]
                    out[i] = prefix[i] + (pair + (c * row_c[i] + d * row_d[i]))
            elif count == 3:
                for i in range(size):
                    out[i] = prefix[i] + ((a * row_a[i] + b * row_b[i]) + c * row_c[i])
            elif count == 2:
                for i in range(size):
                    out[i] = prefix[i] + (a * row_a[i] + b * row_b[i])
            else:
                for i in range(size):
                    out[i] = prefix[i] + a * row_a[i]
        elif count == 4:
            for i in range(size):
                out[i] += (a * row_a[i] + b * row_b[i]) + (c * row_c[i] + d * row_d[i])
        elif count == 3:
            for i in range(size):
                out[i] += (a * row_a[i] + b * row_b[i]) + c * row_c[i]
        elif count == 2:
            for i in range(size):
                out[i] += a * row_a[i] + b * row_b[i]
        else:
            for i in range(size):
                out[i] += a * row_a[i]


@numba.njit(**JIT)
def _best_two(q, s, size, work, rows, best, second, arg):
    """Smallest and second smallest of the costs ``work[prefix] + val q[col, s : s + size]``
    for ``rows = (prefix, col, val)`` (a multiple of four; ties keep the first), four per pass.
    Plain selects, which compile to min and max instructions: NaN costs are skipped, but a
    pixel with any (from a NaN or infinite q) has a non-finite ``Σ_k q_k`` and is never
    certified."""
    prefix, cols, vals = rows
    best[:], second[:], arg[:] = np.inf, np.inf, 0
    for j in range(0, len(prefix), 4):
        row_a, row_b = work[prefix[j]], work[prefix[j + 1]]
        row_c, row_d = work[prefix[j + 2]], work[prefix[j + 3]]
        q_a, q_b = q[cols[j], s : s + size], q[cols[j + 1], s : s + size]
        q_c, q_d = q[cols[j + 2], s : s + size], q[cols[j + 3], s : s + size]
        a, b, c, d = vals[j], vals[j + 1], vals[j + 2], vals[j + 3]
        for i in range(size):
            low, high, label = best[i], second[i], arg[i]
            low, high, label = keep(row_a[i] + a * q_a[i], np.int32(j), low, high, label)
            low, high, label = keep(row_b[i] + b * q_b[i], np.int32(j + 1), low, high, label)
            low, high, label = keep(row_c[i] + c * q_c[i], np.int32(j + 2), low, high, label)
            low, high, label = keep(row_d[i] + d * q_d[i], np.int32(j + 3), low, high, label)
            best[i], second[i], arg[i] = low, high, label


@numba.njit(nogil=True, cache=True, boundscheck=False, error_model="numpy")
def reference_pixels(q, shifted_t, priors, which, labels, start, stop):
    """``reference.reference_labels``, compiled, for pixels ``start:stop`` of (R, N) float32 q
    (exactly p), pixel r with matrix ``which[r]``: ``p / π`` in float64, then each product and
    sum rounded once (no fastmath: called from Python, as numba compiles a callee with its
    caller's flags), ascending k; the first minimum. -1 where a cost is NaN (left to torch's
    reference). ``shifted_t``: (D, N, M) the transposed shifted matrices (M candidates: a defer
    row last)."""
    n, m = shifted_t.shape[1:]
    costs = np.empty(m, np.float64)
    for r in range(start, stop):
        matrix = shifted_t[which[r]]
        costs[:] = 0.0
        for k in range(n):
            x = np.float64(q[r, k]) / priors[k]
            for j in range(m):
                costs[j] = costs[j] + matrix[k, j] * x
        best = 0
        for j in range(m):
            if costs[j] < costs[best]:
                best = j
        labels[r] = -1 if np.isnan(costs).any() else best


@numba.njit(**JIT)
def scratch(rows):
    """The buffers of :func:`decide_block` for a program of ``rows`` rows: ``work`` (its rows of
    sums, zeros first, +inf last), best, second (float32), arg, flags (int32), each of a block."""
    work = np.zeros((rows, BLOCK), np.float32)
    work[rows - 1] = np.inf
    best, second = np.empty(BLOCK, np.float32), np.empty(BLOCK, np.float32)
    return work, best, second, np.empty(BLOCK, np.int32), np.empty(BLOCK, np.int32)


@numba.njit(**JIT)
def decide_block(q, s, program, certificate, buffers, out, size=BLOCK):
    """The block of pixels ``s : s + size`` (``size`` <= BLOCK) of (N, P) float32 q: each pixel's
    row of the argmin written to ``out`` (size,), and ``flags`` of ``buffers`` (:func:`scratch`)
    set to 1 where it is left open (argument meanings: :func:`decide_blocks`)."""
    passes, cols, vals, results, _ = program
    coef, support, reference = certificate
    work, best, second, arg, flags = buffers
    total = work[TOTAL]
    for p in range(len(passes)):
        target, prefix, first, last = passes[p]
        _sums(q, s, size, cols, vals, first, last, work[prefix], work[target])
    _best_two(q, s, size, work, results, best, second, arg)
    for i in range(size):  # M_a <= r_a Σ_k q_k over a's support
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
    buffers, gathered = scratch(program[4]), _opened(q.shape[0])
    for s in range(start, stop, BLOCK):
        gathered = _decide_gather(q, s, BLOCK, program, certificate, buffers, labels, gathered)
    opened, values, count = gathered
    return opened[:count].copy(), values[:count].copy()


@numba.njit(**JIT)
def decide_runs(q, programs, certificates, ids, cuts, labels, start, stop):
    """Pixels ``start:stop`` (from a multiple of ``BLOCK``) of (N, P) float32 q, each decided with
    matrix ``ids[pixel]`` (a regional value system's distinct matrices, docs/definitions.md §21),
    whose program and certificate are ``programs[id]`` and ``certificates[id]`` (typed lists);
    ``cuts``: the pixels whose id differs from the one before, ascending. Returns the pixels
    left open and their (R, N) q, as :func:`decide_blocks` does (argument meanings there).

    The pixels go by runs of one id, each within a block from its start rounded down to a
    multiple of ``VECTOR`` (aligned loads) and decided over a multiple of ``LOOP`` pixels (no
    scalar remainder in the loops): the few pixels beyond the run are decided with its matrix
    and dropped. The runs read q as one stream, whichever matrix decides them, and share one
    scratch (the largest program's rows)."""
    rows = 0
    for program in programs:
        rows = max(rows, program[4])
    buffers = scratch(rows)
    gathered, decided = _opened(q.shape[0]), np.empty(BLOCK, np.int64)
    head = np.empty(VECTOR, np.int64)
    s, previous, c = start, -1, np.searchsorted(cuts, start, side="right")
    program, certificate = programs[0], certificates[0]
    while s < stop:
        d, wide, change = ids[s], s - s % VECTOR, cuts[c] if c < len(cuts) else stop
        end = min(change, wide + BLOCK, stop)
        c += end == change
        last = min(wide + (end - wide + LOOP - 1) // LOOP * LOOP, q.shape[1])
        if d != previous:  # (a typed list's item costs a reference count per array)
            program, certificate, previous = programs[d], certificates[d], d
            buffers[0][program[4] - 1] = np.inf  # its +inf row, maybe another's sums before
        inside = last <= stop  # in place: the pixels after the run are this thread's next runs'
        out = labels[wide:last] if inside else decided[: last - wide]
        head[: s - wide] = labels[wide:s]  # the run before's, put back after
        if last - wide == BLOCK:  # a whole block: the version whose loops have a known length
            decide_block(q, wide, program, certificate, buffers, out)
        else:
            decide_block(q, wide, program, certificate, buffers, out, last - wide)
        labels[wide:s] = head[: s - wide]
        if not inside:
            labels[s:end] = decided[s - wide : end - wide]
        gathered = _gather(q, s, end - s, buffers[4][s - wide :], gathered)
        s = end
    opened, values, count = gathered
    return opened[:count].copy(), values[:count].copy()


@numba.njit(**JIT)
def _opened(n):
    """No pixel left open yet: (opened (1024,) int64, their q (1024, N) float32, count 0)."""
    return np.empty(1024, np.int64), np.empty((1024, n), np.float32), 0


@numba.njit(**JIT)
def _decide_gather(q, s, size, program, certificate, buffers, labels, gathered):
    """Pixels ``s : s + size`` decided into ``labels[s : s + size]`` (:func:`decide_block`), those
    left open appended to ``gathered`` (:func:`_opened`) with their q, while in cache."""
    if size == BLOCK:  # the default: a compiled version whose loops have a known length
        decide_block(q, s, program, certificate, buffers, labels[s : s + BLOCK])
    else:
        decide_block(q, s, program, certificate, buffers, labels[s : s + size], size)
    return _gather(q, s, size, buffers[4], gathered)


@numba.njit(**JIT)
def _gather(q, s, size, flags, gathered):
    """The pixels ``s : s + size`` whose ``flags`` (size,) are 1 (left open) appended to
    ``gathered`` (:func:`_opened`) with their q; ``flags`` is overwritten."""
    opened, values, count = gathered
    unsure = 0
    for i in range(size):  # the pixels left open, gathered (flags[unsure] is free: unsure <= i)
        opened_at = flags[i]
        flags[unsure] = i
        unsure += opened_at
    opened, values = room(opened, values, count + unsure)
    for r in range(unsure):
        opened[count + r] = s + flags[r]
        for k in range(q.shape[0]):
            values[count + r, k] = q[k, s + flags[r]]
    return opened, values, count + unsure


@numba.njit(**JIT)
def room(opened, values, needed):
    """``opened`` (R,) and ``values`` (R, N) grown (to twice, and a block more) when ``needed``
    rows do not fit."""
    if needed <= len(opened):
        return opened, values
    opened = np.concatenate((opened, np.empty(len(opened) + BLOCK, np.int64)))
    values = np.concatenate((values, np.empty((len(values) + BLOCK, values.shape[1]), np.float32)))
    return opened, values
