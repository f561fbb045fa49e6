"""The counts of :func:`~costseg.metrics.functional.mask_segment_errors` from a packed mask's
runs (numba): :func:`~costseg.metrics.functional.rule_errors` takes them where no location maps
are wanted (a sweep: many masks per class and image).

A predicted mask of a smooth label map is a few runs of set bits per row. They are read from the
packed bits a 64-bit word at a time (empty words skipped), joined into 8-connected components
with a union-find over the runs of neighbouring rows, and counted with per-row prefix sums: each
run's pixels per RoI, whether it holds a ground-truth pixel, and the ground-truth components it
meets (from the ground truth's own runs). No pixel is visited one by one: labelling each mask with
``scipy.ndimage.label`` took most of a sweep's segment metrics.
"""

from __future__ import annotations

import numba
import numpy as np

from costseg.metrics.functional.segments import Segments


class Prepared:
    """What every mask of one class and image shares: per-row prefix sums of the RoI ids and of
    the ground-truth mask, and the ground-truth components' runs (row, start, stop, id)."""

    def __init__(self, gt_mask: np.ndarray, roi: np.ndarray | None, num_rois: int, gt: Segments):
        h, w = gt_mask.shape
        r1 = num_rois + 1
        ids = np.zeros((h, w), np.int64) if roi is None else roi.astype(np.int64)
        self.roi_prefix = np.zeros((r1, h, w + 1), np.int32)
        for r in range(r1):
            np.cumsum(ids == r, axis=1, out=self.roi_prefix[r, :, 1:])
        self.gt_prefix = np.zeros((h, w + 1), np.int32)
        np.cumsum(gt_mask, axis=1, out=self.gt_prefix[:, 1:])
        labels = gt.labels.astype(np.int64)
        edges = np.zeros((h, w + 1), bool)  # a run of one component starts at each edge
        edges[:, 0] = labels[:, 0] > 0
        edges[:, 1:-1] = (labels[:, 1:] != labels[:, :-1]) & (labels[:, 1:] > 0)
        row, start = np.nonzero(edges)
        label = labels[row, start]
        stop = start + 1
        _extend(labels, row, stop)
        self.gt_row_start = np.searchsorted(row, np.arange(h + 1)).astype(np.int64)
        self.gt_start, self.gt_stop, self.gt_label = start, stop, label
        self.gt_count, self.gt_owner = gt.count, gt.owner.astype(np.int64)


@numba.njit(nogil=True, cache=True, boundscheck=False)
def _extend(labels, row, stop):
    """Each run's stop: past its last pixel of the same component."""
    w = labels.shape[1]
    for j in range(len(row)):
        y, x, label = row[j], stop[j], labels[row[j], stop[j] - 1]
        while x < w and labels[y, x] == label:
            x += 1
        stop[j] = x


def run_counts(bits: np.ndarray, shape: tuple[int, int], prepared: Prepared) -> np.ndarray:
    """(4, R+1) int64 fp, fn, n_pred, n_gt segments (column 0: whole image) of the (H, W) mask
    packed in ``bits`` (``np.packbits`` of its pixels, row after row)."""
    h, w = shape
    if w % 64:  # rows to whole 64-bit words: each row padded with zeros, which start no run
        mask = np.unpackbits(bits, count=h * w).reshape(h, w)
        bits = np.packbits(np.pad(mask, ((0, 0), (0, -w % 64))), axis=-1)
    words = bits.view(">u8").astype(np.uint64)  # big-endian: the first pixel is the highest bit
    words, p = words.reshape(h, -1), prepared
    return _count(words, p.roi_prefix, p.gt_prefix, p.gt_row_start, p.gt_start, p.gt_stop,
                  p.gt_label, p.gt_count, p.gt_owner)  # fmt: skip


@numba.njit(nogil=True, cache=True, boundscheck=False)
def find_root(parent, i):
    """The root of i's tree in the union-find array ``parent``, halving the path on the way."""
    while parent[i] != i:
        parent[i] = parent[parent[i]]
        i = parent[i]
    return i


@numba.njit(nogil=True, cache=True, boundscheck=False)
def _count(words, roi_prefix, gt_prefix, gt_row_start, gt_start, gt_stop, gt_label, gt_count,
           gt_owner):  # fmt: skip
    h, per_row = words.shape
    r1 = roi_prefix.shape[0]
    cap = 1024
    row, start, stop = np.empty(cap, np.int64), np.empty(cap, np.int64), np.empty(cap, np.int64)
    n, previous = 0, 0  # runs so far; the first run of the previous row
    parent = np.empty(cap, np.int64)
    for y in range(h):
        first = n
        inside = False
        for m in range(per_row):
            word = np.uint64(words[y, m])
            if not inside and word == 0:
                continue
            if inside and word == np.uint64(0xFFFFFFFFFFFFFFFF):
                continue
            for bit in range(64):
                on = (word >> np.uint64(63 - bit)) & np.uint64(1)
                if on and not inside:
                    if n == cap:
                        cap *= 2
                        row, start, stop = _grow(row, cap), _grow(start, cap), _grow(stop, cap)
                        parent = _grow(parent, cap)
                    row[n], start[n], parent[n], inside = y, 64 * m + bit, n, True
                    n += 1
                elif inside and not on:
                    stop[n - 1], inside = 64 * m + bit, False
        if inside:
            stop[n - 1] = 64 * per_row
        j = previous  # runs of the previous row that touch this run (8-connected): union
        for i in range(first, n):
            while j < first and stop[j] < start[i]:
                j += 1
            k = j
            while k < first and start[k] <= stop[i]:
                a, b = find_root(parent, i), find_root(parent, k)
                parent[max(a, b)] = min(a, b)
                k += 1
        previous = first
    votes = np.zeros((n, r1), np.int64)
    hit = np.zeros(n, np.bool_)
    gt_hit = np.zeros(gt_count + 1, np.bool_)
    for i in range(n):
        root, y, x0, x1 = find_root(parent, i), row[i], start[i], stop[i]
        for r in range(r1):
            votes[root, r] += roi_prefix[r, y, x1] - roi_prefix[r, y, x0]
        if gt_prefix[y, x1] > gt_prefix[y, x0]:
            hit[root] = True
            for g in range(gt_row_start[y], gt_row_start[y + 1]):
                if gt_start[g] < x1 and x0 < gt_stop[g]:
                    gt_hit[gt_label[g]] = True
    return tally(votes, parent[:n] == np.arange(n), hit, gt_owner, gt_hit)  # roots: components


@numba.njit(nogil=True, cache=True, boundscheck=False)
def _grow(values, cap):
    larger = np.empty(cap, values.dtype)
    larger[: len(values)] = values
    return larger


@numba.njit(nogil=True, cache=True, boundscheck=False)
def tally(votes, component, hit, gt_owner, gt_hit):
    """(4, R+1) fp, fn, n_pred, n_gt per owning RoI (column 0: all) from each predicted
    component's (rows of ``votes`` where ``component``) pixels per RoI and whether it holds a
    ground-truth pixel, and each ground-truth component's owner and whether it is hit."""
    r1 = votes.shape[1]
    per_owner = np.zeros((4, r1), np.int64)
    for label in range(len(votes)):
        if not component[label]:
            continue
        owner = 0  # the RoI with most pixels; ties to the lowest id
        for r in range(1, r1):
            if votes[label, r] > votes[label, owner]:
                owner = r
        per_owner[2, owner] += 1
        per_owner[0, owner] += not hit[label]
    for g in range(1, len(gt_owner)):
        per_owner[3, gt_owner[g]] += 1
        per_owner[1, gt_owner[g]] += not gt_hit[g]
    counts = per_owner.copy()
    for row in range(4):
        counts[row, 0] = per_owner[row].sum()
    return counts
