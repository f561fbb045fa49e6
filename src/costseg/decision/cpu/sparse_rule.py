"""Single-rule decisions on the CPU in one compiled pass (:mod:`.sparse_kernel`), from a sparse
matrix.

A column constant changes no decision (docs/definitions.md §1), so with ``c_k`` the most
frequent entry of column k, ``C = 1 cᵀ + E`` decides as E: ``argmin_j e_j``, ``e_j = Σ_k E_jk
q_k``. E is sparse for the usual matrices (robotistic: ``-I``; the paper's others add the large
costs of missing a vulnerable class), and rows of the same kind share most entries (the
egoistic matrix's seven static classes differ only on the diagonal). So rows are grouped
(:func:`.row_groups.shared_rows`): a group's shared entries B are summed once per
pixel, each row adds its own rest ``D_j = E_j - B``. A defer row (docs/definitions.md §14) is one
more row, the last candidate: every step below holds for M = N + 1 rows. The sums run over a
block of pixels that stays in cache, up to four terms per pass; each row's last term joins the
pass that keeps the best two.

**Certificate.** The kernel sums ``L = B' + D'_j``, the entries moved down by ``g |.|`` and
rounded down to float32: its float32 sums ``l_j`` lie at or below ``e_j`` whatever their
rounding (``g`` covers the row's depth of rounding and q's three roundings), and within ``d M_j``
of it, ``M_j = Σ_k (|B_k| + |D_jk|) q_k``. The smallest, ``l_a``, certifies the reference's
decision a (float64; within ``eps T`` of exact, T of ``CertifiedCosts``) when every other
``l_b`` exceeds ``l_a + d M_a + 2 eps T``, with ``M_a <= r_a Σ_k q_k`` over the columns of a's
group (``r_a``: the row's largest magnitude), vectorised. A NaN or infinite q makes
``Σ_k q_k`` NaN or infinite: never certified. The pixels left open are decided by the float64
reference itself, on their q gathered while in cache, where q is exactly p (no pixel-wise
priors; float32 and narrower types); else, and for NaN costs, they go to
``CertifiedCosts.settle``. As in the whole decision layer, probabilities are >= 0.
"""

from __future__ import annotations

import math
from functools import lru_cache

import numpy as np
import torch
from numba.typed import List

from costseg.decision import certificate as cert
from costseg.decision.certified import CertifiedCosts
from costseg.decision.cpu.row_groups import PASS, program, shared_rows, supports, with_zeros
from costseg.decision.cpu.sparse_kernel import (
    BLOCK,
    decide_blocks,
    decide_runs,
    reference_pixels,
)
from costseg.workers import in_pieces

CHUNK = 1 << 20  # pixels converted to float32 q at once (other types, pixel-wise priors)


class SparseRule:
    """One matrix's grouped sparse part, float32, and its certificate, for :func:`decide_blocks`.

    Args:
        fast: the matrix's ``CertifiedCosts`` (priors, T's coefficients and ``eps``; the open
            pixels' re-check).
        cost: (1, M, N) float64 cost matrix (M = N, or N + 1 with a defer row, one more
            candidate); shifted: (1, M, N) the reference's.
    """

    def __init__(self, fast: CertifiedCosts, cost: torch.Tensor, shifted: torch.Tensor) -> None:
        m, n = cost.shape[-2:]
        total = fast.weight64[m].cpu()  # T's coefficients: R_k, bounding |reference cost| / q_k
        folded = fast.priors is not None and fast.priors.ndim == 1  # global priors: in E
        priors = fast.priors.cpu().double() if folded else torch.ones(n, dtype=torch.float64)
        matrices = (cost[0], total, priors)
        self.key = (*(x.numpy().tobytes() for x in matrices), fast.eps, m)  # of _prepared
        self.program, self.certificate = _prepared(*self.key)
        # Open pixels: the reference here where q is exactly p (no pixel-wise priors; float32
        # and narrower types), else CertifiedCosts.settle.
        self.reference64 = None
        if fast.pixel_priors is None and fast.probs.dtype != torch.float64:
            self.reference64 = shifted.cpu().transpose(1, 2).contiguous().numpy(), priors.numpy()
        self.step = fast.probs.shape[2] if fast.read_as_is else CHUNK

    def chunk(self, q: torch.Tensor, labels: torch.Tensor) -> torch.Tensor:
        """(N, P) float32 q → (P,) int64 labels written into ``labels``; returns the pixels left
        to ``CertifiedCosts.settle``: those open where q is not exactly p, else those with NaN
        costs."""
        q, n, p = q.contiguous().numpy(), q.shape[0], q.shape[1]
        whole, out, args = p - p % BLOCK, labels.numpy(), (self.program, self.certificate)
        pieces = in_pieces(decide_blocks, (q, *args, out), whole, BLOCK)
        if whole < p:  # the last pixels, padded to a block
            tail = np.zeros((n, BLOCK), np.float32)
            tail[:, : p - whole] = q[:, whole:]
            tail_labels = np.empty(BLOCK, np.int64)
            opened, values = decide_blocks(tail, *args, tail_labels, 0, BLOCK)
            out[whole:] = tail_labels[: p - whole]
            pieces.append((opened[opened < p - whole] + whole, values[opened < p - whole]))
        opened = np.concatenate([part[0] for part in pieces])
        return self.reference(opened, np.concatenate([part[1] for part in pieces]), out)

    def reference(
        self, opened: np.ndarray, values: np.ndarray, out: np.ndarray, threads: bool = True
    ) -> torch.Tensor:
        """The pixels the kernel left ``opened`` (their q: ``values``) decided into ``out`` by
        the compiled reference where q is exactly p (on the threads, or this one); returns the
        pixels left to ``CertifiedCosts.settle``."""
        which = np.zeros(len(opened), np.uint8)
        return reference(self.reference64, opened, values, which, out, threads)


class RegionalRule:
    """A regional value system's distinct matrices (docs/definitions.md §21), each a
    :class:`SparseRule`, deciding the runs of pixels of their RoIs in one pass over the image
    (:func:`.sparse_kernel.decide_runs`), in place."""

    def __init__(self, rules: list[SparseRule]) -> None:
        self.programs, self.certificates = _typed_lists(tuple(rule.key for rule in rules))
        self.reference64 = None  # every rule's or none: the same probabilities and priors
        if rules[0].reference64 is not None:
            shifted = np.concatenate([rule.reference64[0] for rule in rules])
            self.reference64 = shifted, rules[0].reference64[1]

    def chunk(self, q: torch.Tensor, ids: np.ndarray, labels: torch.Tensor) -> torch.Tensor:
        """(N, P) float32 q and (P,) uint8 each pixel's matrix → (P,) int64 labels written into
        ``labels``; returns the pixels left to their matrix's ``CertifiedCosts.settle``."""
        out = labels.numpy()
        cuts = np.flatnonzero(ids[1:] != ids[:-1]) + 1  # where the runs of one id start
        args = (q.contiguous().numpy(), self.programs, self.certificates, ids, cuts, out)
        pieces = in_pieces(decide_runs, args, len(ids), BLOCK)
        opened = np.concatenate([part[0] for part in pieces])
        values = np.concatenate([part[1] for part in pieces])
        return reference(self.reference64, opened, values, ids[opened], out, len(opened) > BLOCK)


def reference(
    reference64, opened: np.ndarray, values: np.ndarray, which, out: np.ndarray, threads: bool
) -> torch.Tensor:
    """The pixels ``opened`` (their q: ``values``, their matrix: ``which``) decided into ``out``
    by the compiled reference where q is exactly p (``reference64``: the (D, N, M) transposed
    shifted matrices and the priors; None: not so), on the threads or this one; returns the
    pixels left to ``CertifiedCosts.settle``."""
    if reference64 is not None and len(opened):
        decided = np.empty(len(opened), np.int64)
        args = (values, *reference64, which, decided)
        if threads:
            in_pieces(reference_pixels, args, len(opened))
        else:
            reference_pixels(*args, 0, len(opened))
        out[opened] = decided
        opened = opened[decided < 0]
    return torch.from_numpy(opened)


@lru_cache(maxsize=32)
def _typed_lists(keys: tuple) -> tuple[List, List]:
    """The programs and certificates of the matrices of :func:`_prepared`'s ``keys`` as numba's
    typed lists, cached (building them takes about 0.5 ms)."""
    programs, certificates = List(), List()
    for key in keys:
        program, certificate = _prepared(*key)
        programs.append(program)
        certificates.append(certificate)
    return programs, certificates


@lru_cache(maxsize=32)
def _prepared(cost: bytes, total: bytes, priors: bytes, eps: float, rows: int) -> tuple:
    """The kernel's program and certificate for a float64 (M, N) matrix (``rows`` M), T's (N,)
    coefficients and (N,) global priors (ones where none), cached: the same matrix comes image
    after image."""
    total, priors = (torch.from_numpy(np.frombuffer(x).copy()) for x in (total, priors))
    n = len(total)
    cost = torch.from_numpy(np.frombuffer(cost).copy()).view(rows, n)
    sparse = cost - cost.mode(0, keepdim=True).values
    sparse, total = sparse / priors, total / priors  # global priors: into the columns
    top = sparse.abs().max().item()
    scale = 2.0 ** -math.frexp(top)[1] if top > 0 else 1.0  # exact: keeps float32 in range
    group, shared, own, magnitude, steps = _grouped(sparse * scale)
    row_gamma = cert.sparse_gamma(steps)  # of row j's float32 sum
    g, g_shared = cert.sparse_lower_g(row_gamma), torch.zeros(len(shared), dtype=torch.float64)
    for index in range(len(shared)):  # a group's shared sum: one g for its rows
        members = group == index
        g[members] = g_shared[index] = g[members].max()
    # Lower bounds of the costs: entries moved down by g |.|, then rounded down.
    shared = cert.round_down32(shared - g_shared[:, None] * shared.abs())
    own = cert.round_down32(own - g[:, None] * own.abs())
    sums, support = supports(magnitude, group)
    plan = program(sums, shared, own, group.numpy())
    # A row's lower bound lies within d M_a of its cost, M_a <= r_a Σ_k q_k over its
    # group's support.
    d = cert.sparse_distance(g, row_gamma)
    reference = 2 * eps * (total * scale).max().item()  # 2 eps T <= this Σ_k q_k
    up = cert.sparse_total_up(_passes(torch.tensor(n)))  # computed Σ_k q_k up to its bound
    coef = (d * magnitude.amax(1) * up).float().numpy()  # of the support's Σ_k q_k
    return plan, (coef, support, np.float32(reference * up))


def _grouped(sparse: torch.Tensor) -> tuple:
    """Rows of an (M, N) matrix grouped by shared entries (:func:`.row_groups.shared_rows`): (M,)
    each row's group, (G, N) the groups' shared entries B, (M, N) the rows' own rest D, (M, N)
    ``|B| + |D|`` and (M,) each row's passes of rounding."""
    group, shared = shared_rows(sparse.numpy())
    group, shared = torch.from_numpy(group), torch.from_numpy(shared)
    base = with_zeros(shared)[group]  # (M, N): each row's B (group -1: the zero row)
    own = sparse - base  # D; B + D = E within u64 |D|, far inside g's 1 % slack
    terms = (own != 0).sum(1)  # the last one in the pass that keeps the best two
    steps = with_zeros(_passes((shared != 0).sum(1)))[group] + _passes(terms - 1) + (terms > 0)
    return group, shared, own, base.abs() + own.abs(), steps


def _passes(terms: torch.Tensor) -> torch.Tensor:
    """Passes of up to four terms for sums of ``terms`` terms."""
    return (terms + PASS - 1) // PASS
