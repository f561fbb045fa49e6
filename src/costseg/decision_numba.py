"""Mixtures decided pixel by pixel in one compiled pass on the CPU (numba).

The same method as :class:`costseg.decision_certified._Mixer`, which runs it as a sequence of
tensor operations over a chunk, each a pass over memory; here each pixel's V vertex costs
(float32, as ``_Fast.costs``, pixel-major) stay in cache while all K mixtures are decided:

1. every vertex's argmin and runner-up, certified as in ``_top`` (gap and floor);
2. where every vertex picks the same class with a certified gap, every mixture picks it;
3. elsewhere the candidates: classes that no vertex winner beats in every vertex by a certain
   margin (``_Mixer._candidates``); a single candidate decides every mixture;
4. else, per mixture, the candidates' mixed costs ``Σ_v w_kv x_v`` and ``T``, their argmin
   (lowest class on ties) and the same certificate with the mixing's rounding in ``γ``.

Pairs left open (and every pair of a pixel whose ``T`` is not finite) go to the float64 re-check,
also compiled (``_settle_pairs``, stage 2), then to the reference. Compiled on first use and
cached beside this file.
"""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor
from functools import cache

import numba
import numpy as np
import torch

from costseg.decision_certified import U64, _Fast, _reference

TINY = 2.0**-120  # as in decision_certified
UNDERFLOW = 2.0**-60  # x_b below it: never certified


@numba.njit(nogil=True, cache=True, boundscheck=False, error_model="numpy")
def _decide_pixels(costs, weights, params, labels, opened, start, stop):
    """Pixels ``start:stop`` of a chunk; returns how many (mixture, pixel) pairs are open.

    Args:
        costs: (P, V, N + 1) float32 vertex costs, pixel-major (a pixel's are adjacent); T last.
        weights: (V, K) float32 mixture weights.
        params: float64 [vertex Δ, vertex floor, candidate slack, candidate T factor,
            mixture Δ, mixture floor].
        labels: (K, P) output, of any integer type; opened: (P, K) uint8, zeroed (pixel-major:
            only contested pixels write it).
    """
    v_count, n, k_count = costs.shape[1], costs.shape[2] - 1, weights.shape[1]
    v_delta, v_floor, slack, t_factor = params[0], params[1], params[2], params[3]
    m_delta, m_floor = np.float32(params[4]), np.float32(params[5])  # rounded up in params
    winner = np.empty(v_count, np.int64)
    candidates = np.empty(n, np.int64)
    beaten, by_winner = np.empty(n, np.float32), np.empty(n, np.float32)
    mix_t = np.empty(k_count, np.float32)  # per mixture: T, a candidate's cost, best, runner-up
    mix_y, mix_best, mix_second = np.empty_like(mix_t), np.empty_like(mix_t), np.empty_like(mix_t)
    mix_arg = np.empty_like(mix_t)  # the best's class
    total = 0
    for j in range(start, stop):
        finite, agree = True, True
        for v in range(v_count):
            t = costs[j, v, n]
            finite = finite and t < np.inf  # False for inf and NaN
            best, second, arg = costs[j, v, 0], np.float32(np.inf), 0
            for c in range(1, n):  # branch-free: these comparisons are unpredictable
                x = costs[j, v, c]
                second = np.minimum(second, np.maximum(x, best))
                arg += (c - arg) * (x < best)
                best = np.minimum(x, best)
            winner[v] = arg
            gap_ok = second - best > v_delta * second
            agree = agree and arg == winner[0] and gap_ok and second >= v_floor * t + UNDERFLOW
        if not finite:
            for k in range(k_count):
                opened[j, k] = 1
            total += k_count
            continue
        if agree:
            for k in range(k_count):
                labels[k, j] = winner[0]
            continue
        # Classes that some vertex winner beats in every vertex by a certain margin (as in
        # _Mixer._candidates): the rest are the candidates. Vectorised over classes.
        beaten[:] = 0
        for u in range(v_count):
            if winner[u] in winner[:u]:  # the same class as an earlier winner
                continue
            by_winner[:] = 1
            for v in range(v_count):
                x_a, t = costs[j, v, winner[u]], costs[j, v, n]
                threshold = (x_a * (1 + slack) + t * t_factor + TINY) / (1 - slack)
                for c in range(n):
                    by_winner[c] *= np.float32(costs[j, v, c] > threshold)
            for c in range(n):
                beaten[c] = np.maximum(beaten[c], by_winner[c])
        m = 0
        for c in range(n):
            if beaten[c] == 0:  # never beaten by itself: each winner is a candidate
                candidates[m] = c
                m += 1
        if m == 1:
            for k in range(k_count):
                labels[k, j] = candidates[0]
            continue
        # Every mixture at once, vectorised over k (np.minimum / np.maximum and arithmetic
        # selects vectorise; Python's min, max and conditional expressions do not).
        for k in range(k_count):
            mix_t[k], mix_best[k], mix_second[k], mix_arg[k] = 0, np.inf, np.inf, candidates[0]
        for v in range(v_count):
            x = costs[j, v, n]
            for k in range(k_count):
                mix_t[k] += weights[v, k] * x
        for i in range(m):
            c = candidates[i]
            for k in range(k_count):
                mix_y[k] = 0
            for v in range(v_count):
                x = costs[j, v, c]
                for k in range(k_count):
                    mix_y[k] += weights[v, k] * x
            label = np.float32(c)
            for k in range(k_count):  # candidates in class order: ties keep the lower class
                y, b = mix_y[k], mix_best[k]
                mix_second[k] = np.minimum(mix_second[k], np.maximum(y, b))
                mix_best[k] = np.minimum(y, b)
                mix_arg[k] += (label - mix_arg[k]) * np.float32(y < b)
        for k in range(k_count):  # 1 where open, into mix_y
            second = mix_second[k]
            gap_ok = second - mix_best[k] > m_delta * second
            floor_ok = second >= m_floor * mix_t[k] + np.float32(UNDERFLOW)
            mix_y[k] = np.float32(1) - np.float32(gap_ok & floor_ok)
        for k in range(k_count):  # K rows apart: not vectorised, kept out of the loops above
            labels[k, j] = np.int64(mix_arg[k])
        flags = int(mix_y.sum())
        if flags:
            total += flags
            for k in range(k_count):
                opened[j, k] = np.uint8(mix_y[k])
    return total


@numba.njit(nogil=True, cache=True, boundscheck=False, error_model="numpy")
def _settle_pairs(costs, weights, grid, pixel, gamma, eps, labels, unsure, start, stop):
    """Stage 2 for (mixture, pixel) pairs ``start:stop``: ``_top64`` on the mixed float64 costs.

    Args:
        costs: (U, V, N + 1) float64 vertex costs of the U pixels (T last); weights: (K, V).
        grid, pixel: (R,) each pair's mixture and row of ``costs``.
        gamma: the rounding of the mixed costs; eps: the reference's, per T.
        labels, unsure: (R,) outputs.
    """
    v_count, n = costs.shape[1], costs.shape[2] - 1
    g = gamma / (1 - gamma)
    for r in range(start, stop):
        k, u = grid[r], pixel[r]
        total = 0.0
        for v in range(v_count):
            total += weights[k, v] * costs[u, v, n]
        lo, hi, arg = np.inf, np.inf, 0
        for c in range(n):
            y = 0.0
            for v in range(v_count):
                y += weights[k, v] * costs[u, v, c]
            if y < lo:  # the first minimum, as torch's min
                lo, hi, arg = y, lo, c
            elif y < hi:
                hi = y
        need = 1.25 * (g * (lo + hi) + 2 * eps * (1 + g) * total) + 2.0**-900
        labels[r] = arg
        unsure[r] = not (total < np.inf and (hi - lo) * (1 - 4 * 2.0**-53) > need)


class NumbaMixer:
    """Decisions of K mixtures, chunk by chunk, on the CPU's cores (see the module docstring).

    Args:
        fast: the vertices' ``_Fast`` (matrices, rounding ``γ`` of their costs, ``eps``).
        weights: (K, V) mixture weights.
        mix_gamma: the rounding of the mixed costs (``_Mixer.gamma``).
    """

    def __init__(
        self, fast: _Fast, weights: torch.Tensor, mix_gamma: float, shifted: torch.Tensor
    ) -> None:
        self.fast, self.weights = fast, weights.t().float().contiguous().numpy()  # (V, K)
        self.weights64, self.shifted = weights.double().contiguous().numpy(), shifted
        v = len(self.weights)  # the float64 re-check: V more nonnegative terms
        self.gamma64 = (1 + fast.gamma64) * (1 + v * U64 / (1 - v * U64)) - 1
        gamma, eps, rounding = fast.gamma, fast.eps, 1 + 2.0**-20  # the float tests' rounding
        self.params = np.array(
            [
                2.5 * gamma / (1 - gamma) * rounding,
                10 * eps / gamma * rounding,
                2 * gamma / (1 - gamma) * 1.01,  # as _Mixer._candidates
                4 * eps,
                2.5 * mix_gamma / (1 - mix_gamma) * rounding,
                10 * eps / mix_gamma * rounding,
            ]
        )

    def chunk(self, q: torch.Tensor, labels: torch.Tensor) -> tuple[torch.Tensor, ...]:
        """(N, P) float32 q → (K, P) labels written into ``labels``; returns the mixtures and
        pixels of the pairs left open."""
        # The vertex costs pixel-major, (P, V, N + 1): each pixel's adjacent.
        costs = (q.detach().t() @ self.fast.weight.t()).view(-1, *self.fast.rows).numpy()
        p, k = costs.shape[0], self.weights.shape[1]
        # Labels of this chunk only: K rows of the whole image lie too far apart (one page
        # each per pixel) for the address translation caches.
        decided = np.empty((k, p), labels.numpy().dtype)
        opened = np.zeros((p, k), np.uint8)  # calloc: pages of contested pixels only are touched
        args = (costs, self.weights, self.params, decided, opened)
        total = sum(_in_pieces(_decide_pixels, args, p))
        labels.copy_(torch.from_numpy(decided))
        if not total:
            return torch.zeros(0, dtype=torch.long), torch.zeros(0, dtype=torch.long)
        pixel, grid = torch.from_numpy(opened).nonzero().unbind(1)
        return grid, pixel

    def settle(self, q: torch.Tensor, grid: torch.Tensor, pixel: torch.Tensor) -> torch.Tensor:
        """Labels (R,) of the pairs left open: stage 2 here, stage 3 (the reference) in torch.

        Args:
            q: (U, N) float64 ``p / π`` of the pixels (``_Fast.exact_q``).
            grid, pixel: (R,) each pair's mixture and row of ``q``.
        """
        fast = self.fast
        costs = (q @ fast.weight64.t()).view(len(q), *fast.rows).numpy()
        labels, unsure = np.empty(len(grid), np.int64), np.empty(len(grid), np.bool_)
        args = (costs, self.weights64, grid.numpy(), pixel.numpy(), self.gamma64, fast.eps)
        _in_pieces(_settle_pairs, (*args, labels, unsure), len(grid))
        labels, unsure = torch.from_numpy(labels), torch.from_numpy(unsure).nonzero()[:, 0]
        if len(unsure):
            matrices = self.shifted[grid[unsure]]
            labels[unsure] = _reference(q[pixel[unsure]], matrices)
        return labels


def _in_pieces(kernel, args: tuple, count: int, align: int = 1) -> list:
    """``kernel(*args, start, stop)`` over ``range(count)`` in a few pieces per thread, each
    starting at a multiple of ``align``."""
    step = max(1, -(-count // (4 * _threads()._max_workers)))
    step = -(-step // align) * align
    pieces = [(s, min(s + step, count)) for s in range(0, count, step)]
    return [job.result() for job in [_threads().submit(kernel, *args, *p) for p in pieces]]


@cache
def _threads() -> ThreadPoolExecutor:
    return ThreadPoolExecutor(len(os.sched_getaffinity(0)), thread_name_prefix="mixtures")


os.register_at_fork(after_in_child=_threads.cache_clear)  # a forked child has none of its threads
