"""How :mod:`.sparse_kernel` sums a matrix's rows: rows grouped by shared entries, the
supports' sums of q for the certificate, and the kernel's program of passes."""

from __future__ import annotations

import numpy as np
import torch

PASS = 4  # terms summed per pass
ZERO, TOTAL = 0, 1  # rows of the kernel's buffer: zeros; Σ_k q_k. Then supports, groups, rows.


def shared_rows(sparse: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Groups of rows with shared entries of an (M, N) matrix: (M,) each row's group (-1: none)
    and (G, N) the groups' shared entries B (per column, a nonzero value that two members or more
    have).

    Greedy: the group that saves the most terms (less a pass per group) is taken first, seeded
    by each free row with the free rows that share two entries or more with it, less those that
    would not save a term."""
    m, n = sparse.shape
    group, shared, free = np.full(m, -1), [], np.ones(m, bool)
    same = ((sparse[:, None] == sparse[None]) & (sparse[None] != 0)).sum(2) >= 2
    while True:
        best = (0, None, None)
        for seed in np.flatnonzero(free):
            members = np.flatnonzero(free & same[seed])
            while len(members) >= 2:  # drop the members that save nothing, until none does
                rows = sparse[members]
                agree = (rows[:, None] == rows[None]).sum(1)  # members with each one's entry
                base = np.where(agree.max(0) >= 2, rows[agree.argmax(0), np.arange(n)], 0.0)
                saves = np.count_nonzero(rows, 1) - np.count_nonzero(rows - base, 1)
                if (saves > 0).all():
                    saving = saves.sum() - np.count_nonzero(base) - PASS
                    if saving > best[0]:
                        best = (saving, members, base)
                    break
                members = members[saves > 0]
        if best[1] is None:
            return group, np.array(shared).reshape(-1, n)
        group[best[1]], free[best[1]] = len(shared), False
        shared.append(best[2])


def program(sums: torch.Tensor, shared: torch.Tensor, own: torch.Tensor, group) -> tuple:
    """``decide_blocks``' program (see there) for (S, N) sums of q (Σ_k q_k, then the
    supports'), (G, N) groups' shared entries, (M, N) rows' own entries (M candidates)."""
    n, first_shared, first_own = len(own), len(sums), len(sums) + len(shared)
    matrix = torch.cat([sums, shared, own])
    ptr, cols, vals = _terms(matrix)
    out = np.arange(len(matrix)) + TOTAL  # work's rows
    prefix = np.full(len(matrix), ZERO)
    prefix[first_own:] = np.where(group >= 0, group + TOTAL + first_shared, ZERO)
    # Each row's last own term joins the pass that keeps the best two (none: 0 × q_0).
    stop, has = ptr[1:].copy(), ptr[first_own + 1 :] > ptr[first_own:-1]
    last = np.where(has, ptr[first_own + 1 :] - 1, 0)
    stop[first_own:] -= has
    fused_cols = np.where(has, cols[last] if len(cols) else 0, 0)
    fused_vals = np.where(has, vals[last] if len(vals) else 0, 0).astype(np.float32)
    some = stop > ptr[:-1]  # passes with terms
    passes = np.stack([out, prefix, ptr[:-1], stop], 1)[some]
    results = np.where(some[first_own:], out[first_own:], prefix[first_own:])
    rows, pad = TOTAL + len(matrix) + 1, -n % 4  # and the +inf row, last
    results = np.concatenate([results, np.full(pad, rows - 1)]).astype(np.int64)
    fused = np.concatenate([fused_cols, np.zeros(pad, np.int64)]).astype(np.int64)
    fused_vals = np.concatenate([fused_vals, np.zeros(pad, np.float32)])
    return passes.astype(np.int64), cols, vals, (results, fused, fused_vals), rows


def supports(magnitude: torch.Tensor, group: torch.Tensor) -> tuple[torch.Tensor, np.ndarray]:
    """Sums of q over the rows' supports (a group's rows: their union), for the vectorised
    certificate: (S, N) their indicators, Σ_k q_k first, and (M,) each row's in ``work`` (M rows
    of (M, N) magnitudes). A row on one column uses Σ_k q_k."""
    support = magnitude != 0
    for index in range(int(group.max()) + 1):
        members = group == index
        support[members] = support[members].any(0)
    support[support.sum(1) < 2] = True
    sums = support.unique(dim=0)
    sums = torch.cat([torch.ones(1, support.shape[1], dtype=torch.bool), sums[~sums.all(1)]])
    rows = (sums[:, None] == support[None]).all(2).int().argmax(0) + TOTAL
    return sums.double(), rows.numpy()


def _terms(matrix: torch.Tensor) -> tuple[np.ndarray, ...]:
    """(ptr, cols, float32 vals) of a float32-exact matrix's nonzero entries, row by row."""
    matrix = matrix.float()
    ptr = np.concatenate([[0], np.cumsum((matrix != 0).sum(1).numpy())])
    rows, cols = matrix.nonzero(as_tuple=True)
    return ptr, cols.numpy(), matrix[rows, cols].numpy()


def with_zeros(values: torch.Tensor) -> torch.Tensor:
    """``values`` and a last row of zeros, which index -1 picks."""
    return torch.cat([values, values.new_zeros(1, *values.shape[1:])])
