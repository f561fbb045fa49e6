"""Which classes can win a pixel's mixtures, for the compiled mixture kernel
(:mod:`.mixture_kernel`): each vertex's certified winner, then the classes that no winner beats
in every vertex by a certain margin (``tensor_ops.Mixer.candidates``, in float32).

Mixed costs are linear in the weights (w >= 0): a class whose costs lie above one winner's in
every vertex lies above it at every mixture, so it is never decided (strictly above, by the
reference's rounding too: not in the reference either).
"""

from __future__ import annotations

import numba
import numpy as np

from costseg.decision.certificate import FLOOR32
from costseg.decision.cpu import VERTICES
from costseg.decision.cpu.block_steps import JIT, U, keep


@numba.njit(**JIT)
def vertex_winners(costs, size, v_count, v_delta, v_floor, best, second, arg, agree, finite):
    """Each of the first ``v_count`` vertices' argmin over classes at pixels ``:size``;
    ``agree``: every vertex picks vertex 0's class with a certified gap; ``finite``: every
    vertex's T is finite."""
    n, size = U(costs.shape[1] - 1), U(size)
    for v in range(U(v_count)):
        best[v, :size], second[v, :size], arg[v, :size] = np.inf, np.inf, 0
        for c in range(U(0), n - n % U(4), U(4)):  # four classes per pass; ties keep the lower c
            c1, c2, c3 = c + U(1), c + U(2), c + U(3)
            for i in range(size):
                x, y, z = best[v, i], second[v, i], arg[v, i]
                x, y, z = keep(costs[v, c, i], np.int32(c), x, y, z)
                x, y, z = keep(costs[v, c1, i], np.int32(c1), x, y, z)
                x, y, z = keep(costs[v, c2, i], np.int32(c2), x, y, z)
                best[v, i], second[v, i], arg[v, i] = keep(costs[v, c3, i], np.int32(c3), x, y, z)
        for c in range(n - n % U(4), n):
            for i in range(size):
                x, y, z = best[v, i], second[v, i], arg[v, i]
                best[v, i], second[v, i], arg[v, i] = keep(costs[v, c, i], np.int32(c), x, y, z)
        for i in range(size):
            low, runner, t = best[v, i], second[v, i], costs[v, n, i]
            gap = (runner - low > v_delta * runner) & (arg[v, i] == arg[0, i])
            sure = gap & (runner >= v_floor * t + np.float32(FLOOR32))
            agree[i] = sure if v == 0 else agree[i] & sure
            finite[i] = (t < np.inf) if v == 0 else finite[i] & (t < np.inf)


@numba.njit(**JIT)
def candidates(costs, size, v_count, coef, arg, threshold, free, count, first):
    """Bit ``c % 32`` of ``free[c // 32, i]``: no vertex winner beats class c at pixel i in
    every vertex by a certain margin: ``x_c > (x_a (1 + slack) + t T + TINY) / (1 - slack)``,
    computed as ``coef · (x_a, T, 1)`` in float32 (coefficients rounded up past its roundings;
    all terms >= 0, so the result lies above the bound); ``count[i]``: how many classes are
    free, ``first[i]``: the lowest. ``costs``: (VERTICES, N + 1, BLOCK), past ``v_count``
    zeros; ``threshold``: (VERTICES, VERTICES, BLOCK) scratch."""
    n = U(costs.shape[1] - 1)
    on_x, on_t, alone = np.float32(coef[0]), np.float32(coef[1]), np.float32(coef[2])
    size = U(size)
    for u in range(U(VERTICES)):
        for v in range(U(VERTICES)):
            if u >= v_count:  # no such winner: beats nothing
                threshold[u, v, :size] = np.inf
            elif v >= v_count:  # no such vertex: every winner beats c in it
                threshold[u, v, :size] = -np.inf
            else:
                for i in range(size):
                    x_a, t = costs[v, U(arg[u, i]), i], costs[v, n, i]
                    threshold[u, v, i] = (on_x * x_a + on_t * t) + alone
    count[:size], free[:, :size] = 0, 0
    for c in range(n):  # VERTICES = 3 written out: one vectorised pass per class
        word, bit = c // U(32), np.uint32(c % U(32))
        for i in range(size):
            x, y, z = costs[0, c, i], costs[1, c, i], costs[2, c, i]
            by_0 = (x > threshold[0, 0, i]) & (y > threshold[0, 1, i]) & (z > threshold[0, 2, i])
            by_1 = (x > threshold[1, 0, i]) & (y > threshold[1, 1, i]) & (z > threshold[1, 2, i])
            by_2 = (x > threshold[2, 0, i]) & (y > threshold[2, 1, i]) & (z > threshold[2, 2, i])
            ok = not (by_0 | by_1 | by_2)
            first[i] = np.int32(c) if ok & (count[i] == 0) else first[i]
            count[i] += np.int32(ok)
            free[word, i] |= np.uint32(ok) << bit
