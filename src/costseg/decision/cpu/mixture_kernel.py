"""The compiled kernel behind :class:`.mixer.NumbaMixer`: K mixtures of V vertex cost maps,
decided block by block of pixels, each step vectorised over a block's pixels.

The method is :class:`costseg.decision.tensor_ops.Mixer`'s, step for step, on the vertices'
float32 costs (``CertifiedCosts.costs``: class-major, T last), computed for each block of pixels
in cache (:func:`.block_steps.block_products`) instead of over the whole image:

1. each vertex's argmin and runner-up, certified as in ``certified.top`` (gap and floor);
2. where every vertex picks the same class with a certified gap, every mixture picks it;
3. elsewhere the candidates (:mod:`.mixture_candidates`): classes that no vertex
   winner beats in every vertex by a certain margin; a single candidate decides every
   mixture;
4. else, per mixture, the candidates' mixed costs ``Σ_v w_kv x_v``, their argmin (the lowest
   class on ties) and the same certificate with the mixing's rounding in ``γ`` (the mixed T
   taken at its bound ``Σ_v w_kv · max_v T_v``: a stricter floor, one load fewer). Up to
   SLOTS candidates per pixel sit side by side in slots (an empty slot costs BIG), so that all
   the block's pixels are mixed in one pass per mixture; pixels with more candidates are
   gathered (in groups by their count: GROUPS, then up to WIDEST) and mixed in passes over
   two slots each.

Pairs left open (and every pair of a pixel whose ``T`` is not finite) get the float64 re-check
(:func:`.block_steps.recheck`) on the pixel's float64 costs where q is exact; those
it leaves open, and all of them where q is not exact, are returned. Compiled on first use and
cached beside this file.
"""

from __future__ import annotations

import numba
import numpy as np

from costseg.decision.certificate import FLOOR32
from costseg.decision.cpu import VERTICES
from costseg.decision.cpu.block_steps import JIT, U, block_products, keep, recheck, trailing_zeros
from costseg.decision.cpu.mixture_candidates import candidates, vertex_winners

BLOCK = 512  # pixels decided together: their vertex costs stay in cache
SLOTS = 4  # candidates mixed side by side for every pixel of a block
MANY = 2048  # pixels with more candidates, gathered to be mixed together, in groups by their
GROUPS = np.array([6, 8, 10, 12])  # count: up to 6 slots, 8, ..., WIDEST (more: left open)
WIDEST = 32  # candidates at most (the slots of the last group)
BIG = np.float32(3.4e38)  # an empty slot's cost: above every real one (w >= 0, some w > 0)


@numba.njit(**JIT, fastmath={"contract"})  # fused multiply-adds: within the mixing's γ
def _mix_slots(xs, ts, cls, size, weights, params, mixed, kept, labels, s, opened, touched):
    """Every mixture of pixels ``:size`` of the slot arrays (costs ``xs`` (VERTICES, SLOTS,
    BLOCK), classes ``cls`` (SLOTS, BLOCK), both flat; the vertices' largest T ``ts``) into
    columns ``s : s + size`` of labels and ``:size`` of opened (``touched``: any mixture's);
    where ``mixed`` is 0 the flags are ``kept``. One pass per mixture: with the slots and the
    vertices fixed, the loop over pixels vectorises; flat arrays with constant strides address
    every slot from one register. The floor test takes the mixed T at its bound ``Σ_v w_v ·
    max_v T_v`` (stricter: a few more pairs left open; its coefficient's margin covers the
    roundings)."""
    m_delta, m_floor = np.float32(params[5]), np.float32(params[6])
    s, size, row = U(s), U(size), U(SLOTS * BLOCK)  # a vertex's slots
    touched[:size] = 0
    for k in range(U(labels.shape[0])):
        w0, w1, w2 = weights[0, k], weights[1, k], weights[2, k]
        floor = m_floor * ((w0 + w1) + w2)  # T <= Σ_v w_v · max_v T_v
        for i in range(size):
            best = (w0 * xs[i] + w1 * xs[row + i]) + w2 * xs[U(2) * row + i]
            second, label = np.float32(np.inf), cls[i]
            for j in range(U(1), U(SLOTS)):  # slots in class order: ties keep the lower class
                at = j * U(BLOCK) + i
                y = (w0 * xs[at] + w1 * xs[row + at]) + w2 * xs[U(2) * row + at]
                c = cls[at]  # loaded either way: a conditional load does not vectorise
                best, second, label = keep(y, c, best, second, label)
            gap_ok = second - best > m_delta * second
            sure = np.uint8(gap_ok & (second >= floor * ts[i] + np.float32(FLOOR32)))
            flag = (np.uint8(1) - sure) & mixed[i] | kept[i]  # never both mixed and kept
            labels[k, s + i], opened[k, i] = label, flag
    for k in range(U(labels.shape[0])):  # apart: fewer stores in the pass above
        for i in range(size):
            touched[i] |= opened[k, i]


@numba.njit(**JIT, fastmath={"contract"})
def _mix_passes(xs, ts, cls, slots, size, weights, params, labels, at, opened, touched):
    """``_mix_slots`` for many slots (a runtime number; past an odd one, the arrays hold an empty
    slot) of gathered pixels, whose labels go to columns ``at[:size]``: one pass over the
    pixels per two slots, every pair open where the certificate fails."""
    m_delta, m_floor = np.float32(params[5]), np.float32(params[6])
    size = U(size)
    best, second = np.empty(size, np.float32), np.empty(size, np.float32)
    label = np.empty(size, np.int32)
    touched[:size] = 0
    for k in range(U(labels.shape[0])):
        w0, w1, w2 = weights[0, k], weights[1, k], weights[2, k]
        floor = m_floor * ((w0 + w1) + w2)  # as _mix_slots
        best[:size], second[:size], label[:size] = np.inf, np.inf, cls[0, :size]
        for j in range(U(0), U(slots), U(2)):  # two per pass, in class order: ties keep the lower
            h = j + U(1)  # past an odd last slot: an empty one (BIG), which changes nothing
            for i in range(size):
                y = (w0 * xs[0, j, i] + w1 * xs[1, j, i]) + w2 * xs[2, j, i]
                z = (w0 * xs[0, h, i] + w1 * xs[1, h, i]) + w2 * xs[2, h, i]
                c, d = cls[j, i], cls[h, i]  # loaded either way: conditional loads do not vectorise
                low, high, arg = keep(y, c, best[i], second[i], label[i])
                best[i], second[i], label[i] = keep(z, d, low, high, arg)
        for i in range(size):
            sec = second[i]
            gap_ok = sec - best[i] > m_delta * sec
            flag = np.uint8(1) - np.uint8(gap_ok & (sec >= floor * ts[i] + np.float32(FLOOR32)))
            opened[k, i] = flag
            touched[i] |= flag
        for i in range(size):  # apart: a scattered store would keep the pass above scalar
            labels[k, U(at[i])] = label[i]


@numba.njit(**JIT)
def _fill_slots(costs, size, free, mixed, count, base, xs, cls):
    """The slots of every pixel of the block: a mixed pixel's candidates (the bits of ``free``),
    then empty slots (cost BIG, class ``base``); other pixels their ``base`` label at cost 0,
    then empty slots."""
    cls[:, :size] = 0
    for i in range(U(size)):  # a mixed pixel's classes, from its bits
        if mixed[i]:
            _classes(free, i, SLOTS, cls, i)
    for j in range(U(SLOTS)):  # vectorised: the costs gathered
        empty = np.float32(0) if j == 0 else BIG
        for i in range(U(size)):
            use = mixed[i] & (j < count[i])
            c = U(cls[j, i])
            cls[j, i] = cls[j, i] if use else base[i]
            xs[0, j, i] = costs[0, c, i] if use else empty
            xs[1, j, i] = costs[1, c, i] if use else empty
            xs[2, j, i] = costs[2, c, i] if use else empty


@numba.njit(inline="always", **JIT)
def _classes(free, i, slots, cls, column):
    """``cls[:, column]``: pixel i's first ``slots`` candidates, from its bits; returns how many."""
    j = 0
    for word in range(free.shape[0]):
        bits = free[word, i]
        while bits and j < slots:
            cls[j, column] = np.int32(32 * word + trailing_zeros(bits))
            bits &= bits - np.uint32(1)
            j += 1
    return j


@numba.njit(inline="always", **JIT)
def _gather_slots(costs, i, free, slots, xs, cls, column):
    """Slots ``column`` of xs and cls from pixel i's candidates (bits of ``free``), gathered
    with many; empty slots cost BIG."""
    filled = _classes(free, i, slots, cls, column)
    for j in range(slots):
        c = cls[j, column]
        for v in range(VERTICES):  # past v_count: zero costs (and zero weights)
            xs[v, j, column] = costs[v, c, i] if j < filled else BIG
        cls[j, column] = c if j < filled else cls[0, column]


@numba.njit(**JIT)
def decide_chunk(
    q, weight, weight64, v_count, weights, weights64, params, labels, column, start, stop
):
    """Pixels ``start:stop`` of a chunk whose first pixel is the image's ``column``.

    Args:
        q: (N, P) float32 ``p / π`` of the chunk's pixels.
        weight: (R, N') float32 ``CertifiedCosts.weight``, zero-padded (see ``block_products``):
            the v_count vertices' costs, class-major, T last, computed block by block in cache.
        weight64: (N, V (N + 1)) float64 the same, transposed, for the float64 re-check where
            q is exact; no columns where it is not (pairs left open are then all returned).
        weights: (VERTICES, K) float32 mixture weights (zeros below the V vertices);
            weights64: (K, V) float64.
        params: float64 [vertex Δ, vertex floor, the candidates' three coefficients
            (``Mixer.candidates``), mixture Δ, mixture floor] (rounded up for the float32 tests),
            the re-check's g and eps (``certify64``).
        labels: (K, H·W) the image's labels, any integer type, written.

    Returns:
        (2, R) int64: the mixture and the chunk's pixel of each pair left open.
    """
    n, k_count = q.shape[0], labels.shape[0]
    # every vertex's rows, zeros past v_count (weight has v_count's, a multiple of four)
    block_costs = np.zeros((max(weight.shape[0], VERTICES * (n + 1)), BLOCK), np.float32)
    costs = block_costs[: VERTICES * (n + 1)].reshape(VERTICES, n + 1, BLOCK)
    v_delta, v_floor = np.float32(params[0]), np.float32(params[1])
    best, second = np.empty((v_count, BLOCK), np.float32), np.empty((v_count, BLOCK), np.float32)
    arg = np.empty((v_count, BLOCK), np.int32)
    agree, finite = np.empty(BLOCK, np.bool_), np.empty(BLOCK, np.bool_)
    threshold = np.empty((VERTICES, VERTICES, BLOCK), np.float32)
    free, count = np.empty((-(-n // 32), BLOCK), np.uint32), np.empty(BLOCK, np.int32)
    base, mixed = np.empty(BLOCK, np.int32), np.empty(BLOCK, np.uint8)
    kept, block_open = np.empty(BLOCK, np.uint8), np.empty((k_count, BLOCK), np.uint8)
    touched = np.empty(MANY, np.uint8)  # pixels with an open pair
    flat_xs = np.zeros(VERTICES * SLOTS * BLOCK, np.float32)  # _mix_slots reads them flat
    flat_cls = np.empty(SLOTS * BLOCK, np.int32)
    xs, cls = flat_xs.reshape(VERTICES, SLOTS, BLOCK), flat_cls.reshape(SLOTS, BLOCK)  # views
    ts = np.zeros(BLOCK, np.float32)
    # Pixels with more candidates than SLOTS, gathered in groups of MANY pixels by their count
    # (up to GROUPS[0], ..., the last one up to WIDEST), each mixed together when full.
    last = len(GROUPS)
    group_xs = np.empty((last + 1, VERTICES, WIDEST, MANY), np.float32)
    group_ts, group_size = np.empty((last + 1, MANY), np.float32), np.zeros(last + 1, np.int64)
    group_cls = np.empty((last + 1, WIDEST, MANY), np.int32)
    group_pixel, widest = np.empty((last + 1, MANY), np.int64), 0  # the last group's most
    flags = np.empty((k_count, MANY), np.uint8)
    pairs, found = np.empty((2, 1024), np.int64), 0
    for s in range(start, stop, BLOCK):
        size = min(BLOCK, stop - s)
        block_products(q, s, size, weight, block_costs)
        vertex_winners(costs, size, v_count, v_delta, v_floor, best, second, arg, agree, finite)
        candidates(costs, size, v_count, params[2:5], arg, threshold, free, count, base)
        for i in range(size):  # agreeing vertices, or a single candidate, decide every mixture
            first, lowest = arg[0, i], base[i]
            base[i] = first if agree[i] else lowest
            contested = finite[i] & (not agree[i]) & (count[i] > 1)
            mixed[i] = contested & (count[i] <= SLOTS)
            kept[i] = (not finite[i]) | (contested & (count[i] > WIDEST))  # open: re-checked
        _fill_slots(costs, size, free, mixed, count, base, xs, cls)
        for i in range(U(size)):  # the vertices' largest T (zeros past v_count)
            ts[i] = max(max(costs[0, n, i], costs[1, n, i]), costs[2, n, i])
        for i in range(size):
            if finite[i] and not agree[i] and SLOTS < count[i] <= WIDEST:
                group = 0
                while group < last and count[i] > GROUPS[group]:
                    group += 1
                e, slots = group_size[group], GROUPS[group] if group < last else WIDEST
                _gather_slots(costs, i, free, slots, group_xs[group], group_cls[group], e)
                group_ts[group, e], group_pixel[group, e], group_size[group] = ts[i], s + i, e + 1
                widest = max(widest, count[i]) if group == last else widest
        mixing = mixed, kept, labels, column + s, block_open, touched
        _mix_slots(flat_xs, ts, flat_cls, size, weights, params, *mixing)
        exact = q, weight64, weights64, params, labels, column  # for the float64 re-check
        opened = block_open, touched, size, np.arange(size) + s
        pairs, found = recheck(*opened, *exact, pairs, found)
        for group in range(last + 1):  # after the block's own labels; room for the next block
            if group_size[group] > MANY - BLOCK or (s + BLOCK >= stop and group_size[group]):
                gathered = group_xs[group], group_ts[group], group_cls[group]
                size, slots = group_size[group], GROUPS[group] if group < last else widest
                pixel = group_pixel[group]
                at = pixel[:size] + column
                _mix_passes(*gathered, slots, size, weights, params, labels, at, flags, touched)
                opened = flags, touched, size, pixel
                pairs, found = recheck(*opened, *exact, pairs, found)
                group_size[group], widest = 0, widest if group < last else 0
    return pairs[:, :found].copy()
