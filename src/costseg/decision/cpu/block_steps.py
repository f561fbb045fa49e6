"""Compiled steps over a block of pixels for the CPU's kernels (:mod:`.sparse_kernel`,
:mod:`.mixture_kernel`): the best two of a run of costs, the vertex costs of a block, the float64
re-check of the pairs a block left open."""

from __future__ import annotations

import numba
import numpy as np
from llvmlite import ir
from numba.extending import intrinsic

from costseg.decision.certificate import FLOOR64, GAP_SHRINK, TEST_MARGIN

JIT = dict(nogil=True, cache=True, boundscheck=False, error_model="numpy")
U = np.uint64  # indices: unsigned ones need no wrap-around of negative values, so 2-D indexing
# vectorises and takes no reference to the array, as a row view does (an atomic count each)


@intrinsic
def trailing_zeros(typing_context, bits):
    """The number of trailing zero bits of an integer (its lowest set bit's index): LLVM's
    cttz, one instruction."""

    def codegen(context, builder, signature, args):
        return builder.cttz(args[0], ir.Constant(ir.IntType(1), 0))

    return bits(bits), codegen


@numba.njit(inline="always", **JIT)
def keep(y, c, low, high, label):
    """Best two after one more cost y of class c: (smallest, second smallest, its class); ties
    keep the earlier class. Plain selects, which compile to min and max instructions: NaN costs
    are skipped, which is safe where a pixel with any is never certified (its T, or its sum of
    q, is not finite)."""
    above = y if y > low else low
    return (y if y < low else low), (above if above < high else high), (c if y < low else label)


@numba.njit(inline="always", **JIT)
def certify64(costs, weights, k, g, eps, mixed):
    """Mixture k's decision at one pixel from its float64 vertex costs (V, N + 1), T last, and
    whether it is unsure: ``certificate.certified64`` on the mixed costs (``mixed``: (N + 1,)
    scratch), ``g = γ / (1 - γ)`` of their rounding, the reference within ``eps T`` (NaN or
    infinite T: unsure)."""
    v_count, n = costs.shape[0], costs.shape[1] - 1
    mixed[:] = 0
    for v in range(v_count):  # vertex by vertex: every class's sum in one vectorised pass
        w = weights[k, v]
        for c in range(n + 1):
            mixed[c] += w * costs[v, c]
    lo, hi, arg, total = np.inf, np.inf, 0, mixed[n]
    for c in range(n):
        y = mixed[c]
        if y < lo:  # the first minimum, as torch's min
            lo, hi, arg = y, lo, c
        elif y < hi:
            hi = y
    need = TEST_MARGIN * (g * (lo + hi) + 2 * eps * (1 + g) * total) + FLOOR64
    return arg, not (total < np.inf and (hi - lo) * GAP_SHRINK > need)


@numba.njit(**JIT)
def recheck(
    flags, touched, size, pixel, q, weight64, weights64, params, labels, column, pairs, found
):
    """The pairs flagged in ``flags[:, :size]`` (pixel ``pixel[i]`` of the chunk; ``touched``:
    the pixels with one): where the (N, R) float64 ``weight64`` has columns, the float64
    re-check (``certify64`` on the pixel's costs ``q @ weight64``), its label written where it
    is sure; the others appended to ``pairs`` (mixture, pixel)."""
    n, rows, v_count = q.shape[0], weight64.shape[1], weights64.shape[1]
    exact, g, eps = rows > 0, params[7], params[8]
    costs, mixed = np.zeros(v_count * (n + 1)), np.empty(n + 1)
    vertex_costs = costs.reshape(v_count, n + 1)
    for i in range(size):
        if not touched[i]:
            continue
        p = pixel[i]
        costs[:rows] = 0
        for c in range(n):  # term by term: every row's sum in one vectorised pass
            x = np.float64(q[c, p])
            for r in range(rows):
                costs[r] += weight64[c, r] * x
        for k in range(flags.shape[0]):
            if not flags[k, i]:
                continue
            if exact:
                label, unsure = certify64(vertex_costs, weights64, k, g, eps, mixed)
                if not unsure:
                    labels[k, column + p] = label
                    continue
            if found == pairs.shape[1]:  # full: twice as large
                larger = np.empty((2, 2 * found), np.int64)
                larger[:, :found] = pairs
                pairs = larger
            pairs[0, found], pairs[1, found] = k, p
            found += 1
    return pairs, found


@numba.njit(**JIT, fastmath={"contract"})
def block_products(q, s, size, weight, out):
    """``out[:, :size] = weight @ q[:, s : s + size]``: float32 (R, N) weights, R and N multiples
    of four (zero padding), four rows and four terms per pass (any order of summation is within
    the dot product of ``CertifiedCosts.gamma``; multiply-adds fused, NaN and inf kept). Indices
    are unsigned (see ``U``)."""
    last, s = U(q.shape[0] - 1), U(s)
    for r in range(U(0), U(weight.shape[0]), U(4)):
        r1, r2, r3 = r + U(1), r + U(2), r + U(3)
        for k in range(U(0), U(weight.shape[1]), U(4)):
            k1, k2, k3 = k + U(1), k + U(2), k + U(3)
            l1, l2, l3 = min(k1, last), min(k2, last), min(k3, last)  # past q: zero weights
            a0, a1, a2, a3 = weight[r, k], weight[r, k1], weight[r, k2], weight[r, k3]
            b0, b1, b2, b3 = weight[r1, k], weight[r1, k1], weight[r1, k2], weight[r1, k3]
            c0, c1, c2, c3 = weight[r2, k], weight[r2, k1], weight[r2, k2], weight[r2, k3]
            d0, d1, d2, d3 = weight[r3, k], weight[r3, k1], weight[r3, k2], weight[r3, k3]
            if k == 0:
                for i in range(U(size)):
                    x, y, z, t = q[k, s + i], q[l1, s + i], q[l2, s + i], q[l3, s + i]
                    out[r, i] = (a0 * x + a1 * y) + (a2 * z + a3 * t)
                    out[r1, i] = (b0 * x + b1 * y) + (b2 * z + b3 * t)
                    out[r2, i] = (c0 * x + c1 * y) + (c2 * z + c3 * t)
                    out[r3, i] = (d0 * x + d1 * y) + (d2 * z + d3 * t)
            else:
                for i in range(U(size)):
                    x, y, z, t = q[k, s + i], q[l1, s + i], q[l2, s + i], q[l3, s + i]
                    out[r, i] += (a0 * x + a1 * y) + (a2 * z + a3 * t)
                    out[r1, i] += (b0 * x + b1 * y) + (b2 * z + b3 * t)
                    out[r2, i] += (c0 * x + c1 * y) + (c2 * z + c3 * t)
                    out[r3, i] += (d0 * x + d1 * y) + (d2 * z + d3 * t)
