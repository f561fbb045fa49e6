"""The compiled fused pass of :mod:`costseg.decision.counts` on the CPU: each block of pixels
decided by the single-rule kernel (:func:`.sparse_kernel.decide_block`), in cache, and counted
at once into confusion counts; no label map is written."""

from __future__ import annotations

import numba
import numpy as np

from costseg.decision.cpu.sparse_kernel import BLOCK, decide_block, room, scratch

JIT = dict(nogil=True, cache=True, boundscheck=False, error_model="numpy")


LANES = 4  # copies of the counts, pixel i into copy i % 4: consecutive pixels of the same cell
# and decision (most of them) then add to different memory, not one chain of dependent adds


@numba.njit(**JIT)
def count_blocks(q, program, certificate, cell, argmax, start, stop):
    """Decide and count pixels ``start:stop`` (whole blocks) of (N, P) float32 q.

    Args:
        q, program, certificate: as in :func:`.sparse_kernel.decide_blocks` (M candidates).
        cell: (P,) int32 the row of the counts of each pixel (image, RoI id, true class); -1:
            counted nowhere (padding), and never decided again.
        argmax: (P,) int32 each pixel's argmax of p.

    Returns:
        ``first``, the counts' first row; (rows, M + 1) int64 counts of the cells
        ``first : first + rows`` of the certified pixels: decisions 0..M-1, then the pixels whose
        decision is their argmax; the pixels left open, (R,) int64, and their (R, N) q.
    """
    n, m = q.shape[0], len(certificate[0])
    first, last = np.int64(1) << 62, np.int64(-1)
    for i in range(start, stop):  # the cells of this piece: a contiguous range of images
        c = np.int64(cell[i])
        if c >= 0:
            first, last = min(first, c), max(last, c)
    first = min(first, last + 1)
    rows, width = last + 1 - first, m + 1
    lanes = np.zeros((LANES, (rows + 1) * width), np.int32)  # a last row for the uncounted
    spare = rows * width
    buffers = scratch(program[4])
    flags, labels, index = buffers[4], np.empty(BLOCK, np.int64), np.empty(BLOCK, np.int64)
    opened, count = np.empty(1024, np.int64), 0
    values = np.empty((1024, n), np.float32)
    for s in range(start, stop, BLOCK):
        decide_block(q, s, program, certificate, buffers, labels)
        unsure = 0
        for i in range(BLOCK):  # left open: decided again exactly, by the caller
            c = cell[s + i]
            index[unsure] = i
            unsure += flags[i] & (c >= 0)
            base = (c - first) * width if (c >= 0) & (flags[i] == 0) else spare
            label = labels[i]
            lanes[i % LANES, base + label] += 1
            lanes[i % LANES, base + m] += label == argmax[s + i]
        opened, values = room(opened, values, count + unsure)
        for r in range(unsure):
            opened[count + r] = s + index[r]
            for k in range(n):
                values[count + r, k] = q[k, s + index[r]]
        count += unsure
    counts = lanes.astype(np.int64).sum(0)[:spare].reshape(rows, width)
    return first, counts, opened[:count].copy(), values[:count].copy()
