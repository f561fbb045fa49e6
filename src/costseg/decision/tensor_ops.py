"""The fast path in torch tensor operations, on any device (docs/definitions.md §1).

A single rule: float32 costs, one matmul per chunk of pixels that stays in cache, certified by
:func:`~.certified.top`. Mixtures ``Σ_v w_kv C_v`` (``w >= 0``): the cost is linear in C, and
the vertices' shifts differ from the mixture's by a column constant, so the V vertex cost maps
are computed once and mixed (:class:`Mixer`). Where every vertex picks the same class with a
certified gap, so does every mixture. Elsewhere only classes that no vertex winner beats in
every vertex can win; two or three such candidates are decided by the signs of mixed cost
differences, more by mixing their costs; the pairs left open go to
:meth:`~.certified.CertifiedCosts.settle` on the mixed matrices of ``mix_costs``. A defer row
(docs/definitions.md §14) is one more candidate, after the classes, everywhere. A regional value
system (§21): each distinct matrix decides its pixels, gathered (:func:`~.regions.by_region`).
"""

from __future__ import annotations

import functools
from collections.abc import Callable

import torch

from costseg.decision import certificate as cert
from costseg.decision import certified
from costseg.decision.certified import CertifiedCosts, top
from costseg.decision.regions import by_region

NAME = "torch"


def not_supported_reasons(inputs) -> list[str]:
    """None: tensor operations run on every device, for every input."""
    return []


def decide(probs: torch.Tensor, cost: torch.Tensor, priors) -> torch.Tensor:
    """(B, H, W) rows of the argmin of one (1, M, N) float64 matrix, M = N or N + 1 with a defer
    row (inputs checked by ``decide``)."""
    fast, out, shifted = certified.single_rule(probs, cost, priors)

    def chunk(q: torch.Tensor, labels: torch.Tensor) -> torch.Tensor:
        _, open_ = top(fast.costs(q)[0], fast.gamma, fast.eps, *fast.code, True, labels)
        return open_.nonzero()[:, 0]

    certified.decide_in_chunks(fast, out, None, chunk, shifted)
    return out.view(len(probs), *probs.shape[2:])


decide_regional = by_region(decide)
"""(B, H, W) rows of a regional value system's argmins: (K, M, N) stack, (B', H, W) RoI ids."""


def decide_mixtures(probs, vertices, weights, priors) -> torch.Tensor:
    """(B, K, H, W) rows of the argmins of K mixtures (inputs checked by ``decide_mixtures``)."""
    fast, out, mixed, weights64 = certified.mixtures(probs, vertices, weights, priors)
    mix = Mixer(weights64(), fast, mixed())
    for i in range(len(probs)):
        for s, q in fast.chunks(i):
            exact_q = lambda pixels, i=i, s=s: fast.exact_q(i, s + pixels)  # noqa: E731
            mix.chunk(fast.costs(q), exact_q, out[i, :, s : s + q.shape[1]])
    return out.view(len(probs), len(weights), *probs.shape[2:])


class Mixer:
    """Certified decisions of K mixtures of V vertex matrices, chunk by chunk (see the module
    docstring)."""

    def __init__(self, weights: torch.Tensor, fast: CertifiedCosts, mixed: torch.Tensor) -> None:
        self.weights64, self.weights, self.fast, self.mixed = weights, weights.float(), fast, mixed
        v = weights.shape[1]
        self.gamma = cert.mixed_gamma(fast.gamma, fast.u_in, v)  # mixed costs (and T)
        self.slack = cert.signs_slack(fast.gamma, fast.u_in, v, fast.eps)  # of signs()

    def chunk(self, costs: torch.Tensor, exact_q: Callable, labels: torch.Tensor) -> None:
        """Vertex costs (V, M + 1, P) of a chunk (M rows, then T) → its (K, P) rows."""
        fast, k, p = self.fast, len(self.weights), costs.shape[2]
        winner, open_ = top(costs, fast.gamma, fast.eps, *fast.code)
        contested = ((winner != winner[:1]).any(0) | open_.any(0)).nonzero()[:, 0]
        if not len(contested):
            labels.copy_(winner[:1].expand(k, -1))
            return
        # Pixel j's labels will sit in column source[j] of table = [winner-0 labels, mixed]:
        # a gather, much faster than scattering K labels per contested pixel.
        table = torch.empty(k, p + len(contested), dtype=labels.dtype, device=labels.device)
        table[:, :p] = winner[:1]
        picked = costs.view(-1, p).index_select(1, contested).view(*costs.shape[:2], -1)
        order, grid, column = self.groups(picked, winner[:, contested].long(), table[:, p:])
        if len(grid):
            pixels, inverse = torch.unique(contested[order[column]], return_inverse=True)
            settled = fast.settle(exact_q(pixels), self.mixed, grid, self.weights64, inverse)
            table[grid, p + column] = settled.to(labels.dtype)
        source = torch.arange(p, device=labels.device)
        source[contested[order]] = p + torch.arange(len(order), device=labels.device)
        labels.copy_(table.gather(1, source.expand(k, -1)))

    def groups(self, costs: torch.Tensor, winner: torch.Tensor, table: torch.Tensor):
        """Labels of contested pixels, grouped by their number of candidates, into ``table``.

        Returns:
            the pixels' order (P,) and the (mixture, column) pairs left open.
        """
        candidate = self.candidates(costs, winner)
        count = candidate.sum(0)
        k, v, n, p = *self.weights.shape, costs.shape[1] - 1, costs.shape[2]
        order, redo, start = [], [], 0
        for m in count.unique().tolist():
            sel = (count == m).nonzero()[:, 0]
            classes = candidate.index_select(1, sel).t().nonzero()[:, 1].view(-1, m).t()
            columns, order = table[:, start : start + len(sel)], [*order, sel]
            if m == 1:
                columns.copy_(classes.expand(k, -1))
            else:
                rows = torch.cat([classes, torch.full_like(classes[:1], n)])  # candidates, T
                picked = costs.view(v, -1).index_select(1, (rows * p + sel).flatten())
                method = self.signs if m <= 3 else self.many
                labels, unsure = method(picked.view(v, m + 1, -1), classes)
                columns.copy_(labels)
                screen = unsure.any(0).nonzero()[:, 0]  # open pairs are rare: screen pixels
                grid, column = unsure[:, screen].nonzero().unbind(1)
                redo.append(torch.stack([grid, screen[column] + start]))
            start += len(sel)
        redo = torch.cat(redo, 1) if redo else count.new_zeros(2, 0)
        return torch.cat(order), redo[0], redo[1]

    def many(self, picked: torch.Tensor, classes: torch.Tensor):
        """(V, m + 1, P) candidate costs and T, (m, P) classes → labels (K, P), open (K, P)."""
        k, v = self.weights.shape
        mixed = (self.weights @ picked.view(v, -1)).view(k, len(picked[0]), -1)
        return top(mixed, self.gamma, self.fast.eps, classes.int(), self.fast.code[1], True)

    def signs(self, picked: torch.Tensor, classes: torch.Tensor):
        """``many`` for two or three candidates: signs of mixed differences ``x_j - x_i``.

        Per pair i < j: ``lo = w · (d - s)`` and ``-hi = -w · (d + s)``, ``d = x_j - x_i``, with
        the slack ``s`` covering the rounding of x (relative to ``x_i + x_j``), of these float32
        operations and the reference's (``eps T``): ``lo > 0`` certifies i over j in the
        reference, ``-hi > 0`` j over i, never both. A class certified over all others wins.
        """
        (k, v), m = self.weights.shape, len(classes)
        *x, total = picked.unbind(1)
        rows = []
        for i, j in [(0, 1), (0, 2), (1, 2)][: 3 * (m - 2) + 1]:
            slack = torch.add((x[i] + x[j]).mul_(self.slack[0]), total, alpha=self.slack[1])
            slack += cert.TINY
            rows += [x[j] - x[i] - slack, (x[j] - x[i] + slack).neg_()]
        signs = (self.weights @ torch.stack(rows, 1).view(v, -1)).view(k, len(rows), -1)
        if m == 2:
            wins = signs.unbind(1)  # a over b, b over a
        else:  # a over b and c, b over a and c, c over a and b
            wins = [torch.minimum(signs[:, i], signs[:, j]) for i, j in [(0, 2), (1, 4), (3, 5)]]
        best = functools.reduce(torch.maximum, wins)  # > 0: certain; NaN: not
        # The last class unless an earlier one wins (bit pattern >= 1: positive; -0.0 is INT_MIN).
        classes = classes.int()
        labels = classes[-1]
        for i in range(m - 1):
            won = wins[i].view(torch.int32).clamp(0, 1)
            labels = won.mul_(classes[i] - classes[-1]).add_(labels)
        return labels, ~(best > 0)

    def candidates(self, costs: torch.Tensor, winner: torch.Tensor) -> torch.Tensor:
        """(N, P) bool: classes that no vertex winner beats in every vertex by a certain margin.

        A class beaten by the same class in every vertex is beaten at every mixture (w >= 0),
        in the reference too, so it can never be the decision. "Certain": ``x_j - x_a`` exceeds
        twice the rounding of both (relative) and of the reference (``eps T``).
        """
        costs, total = costs[:, :-1], costs[:, -1:]
        slack = cert.candidates_slack(self.fast.gamma)
        extra = total * (4 * self.fast.eps) + cert.TINY
        beaten = None  # max over winners a of min over vertices of x_j - threshold_a (> 0: beaten)
        for best in winner:
            chosen = costs.gather(1, best.expand(costs.shape[0], 1, -1))
            margin = (costs - (chosen * (1 + slack) + extra) / (1 - slack)).amin(0)
            beaten = margin if beaten is None else torch.maximum(beaten, margin)
        return ~(beaten > 0)  # NaN: a candidate
