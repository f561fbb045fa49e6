"""Compiled steps over a block of pixels that the CPU's decision kernels share
(:mod:`costseg.decision_sparse`, :mod:`costseg.decision_mixing`)."""

from __future__ import annotations

import numba

JIT = dict(nogil=True, cache=True, boundscheck=False, error_model="numpy")


@numba.njit(inline="always", **JIT)
def keep(y, c, low, high, label):
    """Best two after one more cost y of class c: (smallest, second smallest, its class); ties
    keep the earlier class. Plain selects, which compile to min and max instructions: NaN costs
    are skipped, which is safe where a pixel with any is never certified (its T, or its sum of
    q, is not finite)."""
    above = y if y > low else low
    return (y if y < low else low), (above if above < high else high), (c if y < low else label)


@numba.njit(**JIT, fastmath={"contract"})
def block_products(q, s, size, weight, out):
    """``out[:, :size] = weight @ q[:, s : s + size]``: float32 (R, N) weights, R a multiple of
    four and N even (zero padding), four rows and two terms per pass (any order of summation
    is within ``_Fast.gamma``'s dot product; multiply-adds fused, NaN and inf kept)."""
    for r in range(0, weight.shape[0], 4):
        out_a, out_b, out_c, out_d = out[r], out[r + 1], out[r + 2], out[r + 3]
        for k in range(0, weight.shape[1], 2):
            q_k, q_l = q[k, s : s + size], q[min(k + 1, q.shape[0] - 1), s : s + size]
            a, b, c, d = weight[r, k], weight[r + 1, k], weight[r + 2, k], weight[r + 3, k]
            e, f = weight[r, k + 1], weight[r + 1, k + 1]
            g, h = weight[r + 2, k + 1], weight[r + 3, k + 1]
            if k == 0:
                for i in range(size):
                    out_a[i], out_b[i] = a * q_k[i] + e * q_l[i], b * q_k[i] + f * q_l[i]
                    out_c[i], out_d[i] = c * q_k[i] + g * q_l[i], d * q_k[i] + h * q_l[i]
            else:
                for i in range(size):
                    out_a[i] += a * q_k[i] + e * q_l[i]
                    out_b[i] += b * q_k[i] + f * q_l[i]
                    out_c[i] += c * q_k[i] + g * q_l[i]
                    out_d[i] += d * q_k[i] + h * q_l[i]
