"""MetaSeg's segment features of one image (numba): per predicted segment its size, interior and
boundary, the means of heat maps and of the class probabilities, its class and centroid, and
(with a ground truth) the targets: the adjusted IoU and whether it is a false positive.

Segments are the 8-connected components of equal label of the label map, where pixels of label
255 (deferred, or ignored in the ground truth: they are set to 255 first) belong to none. They
are numbered 1, 2, ... in row-major order of their first pixel, over all classes together. A
segment pixel is a boundary pixel if one of its 8 neighbours inside the image has another label
(255 included; the image's edge makes no boundary), else an interior pixel.

The adjusted IoU of a segment of class ``c`` is ``I / U``: ``I`` its pixels whose ground truth
is ``c``; ``U`` its size plus the sizes of the 8-connected components of
``(gt == c) & (labels != c)`` that have a pixel next to it (8-neighbours), each counted once.

>>> labels = np.array([[0, 0, 1], [0, 1, 1], [2, 2, 2]], np.uint8)
>>> probs = np.full((3, 3, 3), 1 / 3, np.float32)
>>> heat = {"E": np.ones((3, 3), np.float32)}
>>> gt = np.array([[0, 0, 0], [0, 1, 1], [2, 2, 255]], np.uint8)
>>> table = segment_features(labels, probs, heat, gt)
>>> table.count, table.ids.tolist()
(3, [[1, 1, 2], [1, 2, 2], [3, 3, 0]])
>>> table.columns["S"].tolist(), table.columns["S_bd"].tolist()
([3.0, 3.0, 2.0], [3.0, 3.0, 2.0])
>>> table.columns["iou"].tolist()  # segment 1 misses gt (0, 2): U = 3 + 1
[0.75, 0.6666666666666666, 1.0]
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numba
import numpy as np

from costseg.metrics.segment_runs import find_root

FEATURES_OF_SIZE = ("S", "S_in", "S_bd", "S_rel", "S_rel_in")
HEAT_SUFFIXES = ("", "_in", "_bd", "_rel", "_rel_in")
TARGETS = ("iou", "iou0")
NONE = 255
"""The label of pixels that belong to no segment (and the ground truth's ignored label)."""


def feature_names(heat_names: Sequence[str], num_classes: int) -> list[str]:
    """The feature columns in order: FEATURES_OF_SIZE, then per heat map name h: h, h_in, h_bd,
    h_rel, h_rel_in; then cprob0..cprob{N-1}; then "class", "row", "col"."""
    names = list(FEATURES_OF_SIZE)
    names += [h + suffix for h in heat_names for suffix in HEAT_SUFFIXES]
    names += [f"cprob{k}" for k in range(num_classes)]
    return [*names, "class", "row", "col"]


@dataclass
class SegmentTable:
    """The segments of one image and their features."""

    ids: np.ndarray
    """(H, W) int32 segment id per pixel, 0 = no segment."""
    columns: dict[str, np.ndarray]
    """Every feature name (and the TARGETS when a ground truth was given) -> (n,) float64; row i
    is segment i + 1."""

    @property
    def count(self) -> int:
        """The number of segments."""
        return len(self.columns["S"])


def painted(ids: np.ndarray, values: np.ndarray) -> np.ndarray:
    """(H, W) float64: each pixel's segment's value (segment i = ``values[i - 1]``), NaN off any
    segment.

    >>> painted(np.array([[1, 1, 0], [2, 2, 2]]), np.array([0.25, 1.0])).tolist()
    [[0.25, 0.25, nan], [1.0, 1.0, 1.0]]
    """
    lookup = np.concatenate([[np.nan], np.asarray(values, np.float64)])
    return lookup[ids]


def segment_features(
    labels: np.ndarray,
    probs: np.ndarray,
    heat: Mapping[str, np.ndarray],
    gt: np.ndarray | None = None,
) -> SegmentTable:
    """The segments of ``labels`` (H, W) integer (255 = no class) and their features from
    ``probs`` (N, H, W) float32 and ``heat`` (name -> (H, W) float32), with the targets when
    ``gt`` (H, W) integer (255 = ignored) is given.

    Where a segment has no boundary pixel (a map of one label everywhere) S_rel and S_rel_in
    divide by 1 instead of S_bd = 0, and the boundary means are 0 (as are the interior means of a
    segment without interior).
    """
    shape = labels.shape
    if labels.ndim != 2:
        raise ValueError(f"labels of shape {shape}, not (H, W)")
    if probs.ndim != 3 or probs.shape[1:] != shape:
        raise ValueError(f"probs of shape {probs.shape} for labels of shape {shape}")
    names = list(heat)
    for name in names:
        if heat[name].shape != shape:
            raise ValueError(f"heat map {name!r} of shape {heat[name].shape}, not {shape}")
    lab = labels.astype(np.int32)  # one compiled variant for every integer type
    if gt is not None:
        if gt.shape != shape:
            raise ValueError(f"gt of shape {gt.shape} for labels of shape {shape}")
        gt = gt.astype(np.int32)
        lab[gt == NONE] = NONE
    p = np.ascontiguousarray(probs, dtype=np.float32)
    h_stack = np.empty((len(names), *shape), np.float32)
    for m, name in enumerate(names):
        h_stack[m] = heat[name]
    ids, n = _label(lab)
    out = _accumulate(lab, ids, n, p, h_stack, lab if gt is None else gt, gt is not None)
    count, bd, heat_all, heat_in, heat_bd, prob, cls, rows, cols, inter, edges = out
    s = count.astype(np.float64)
    s_bd = bd.astype(np.float64)
    s_in = s - s_bd
    div = np.maximum(s_bd, 1.0)  # no boundary: divide by 1
    s_rel, s_rel_in = s / div, s_in / div
    columns = {"S": s, "S_in": s_in, "S_bd": s_bd, "S_rel": s_rel, "S_rel_in": s_rel_in}
    for m, name in enumerate(names):
        mean = heat_all[:, m] / s
        mean_in = np.divide(heat_in[:, m], s_in, out=np.zeros(n), where=s_in > 0)
        columns[name] = mean
        columns[name + "_in"] = mean_in
        columns[name + "_bd"] = np.divide(heat_bd[:, m], s_bd, out=np.zeros(n), where=s_bd > 0)
        columns[name + "_rel"] = mean * s_rel
        columns[name + "_rel_in"] = mean_in * s_rel_in
    for k in range(p.shape[0]):
        columns[f"cprob{k}"] = prob[:, k] / s
    columns["class"] = cls
    columns["row"], columns["col"] = rows / s, cols / s
    if gt is not None:  # the ground truth of class c not predicted c: what widens the union
        missed = np.where(lab != gt, gt, NONE).astype(np.int32)
        m_ids, m_n = _label(missed)
        sizes = np.bincount(m_ids.ravel(), minlength=m_n + 1).astype(np.int64)
        columns["iou"] = inter / _union(lab, ids, count, edges, missed, m_ids, sizes)
        columns["iou0"] = (inter == 0).astype(np.float64)
    return SegmentTable(ids, columns)


@numba.njit(nogil=True, cache=True, boundscheck=False)
def _join(parent, i, j):
    """Joins the trees of i and j; the smaller index is the root (a component's first pixel)."""
    a, b = find_root(parent, i), find_root(parent, j)
    if a < b:
        parent[b] = a
    elif b < a:
        parent[a] = b


@numba.njit(nogil=True, cache=True, boundscheck=False)
def _label(lab):
    """(H, W) int32 ids of the 8-connected components of equal label (255: none, id 0), numbered
    1, 2, ... in row-major order of their first pixel, and their number."""
    h, w = lab.shape
    parent = np.empty(h * w, np.int32)
    for y in range(h):
        for x in range(w):
            i = y * w + x
            parent[i] = i
            v = lab[y, x]
            if v == NONE:
                continue
            # the neighbours scanned before: left, up-left, up, up-right
            if y > 0 and lab[y - 1, x] == v:  # up touches up-left, up-right and left already
                _join(parent, i, i - w)
                continue
            if x > 0 and lab[y, x - 1] == v:  # left touches up-left already
                _join(parent, i, i - 1)
            elif x > 0 and y > 0 and lab[y - 1, x - 1] == v:
                _join(parent, i, i - w - 1)
            if y > 0 and x + 1 < w and lab[y - 1, x + 1] == v:
                _join(parent, i, i - w + 1)
    ids = np.zeros((h, w), np.int32)
    flat = ids.ravel()
    n = 0
    for i in range(h * w):  # a root is its component's first pixel: seen before the others
        if lab[i // w, i % w] == NONE:
            continue
        r = find_root(parent, i)
        if r == i:
            n += 1
            flat[i] = n
        else:
            flat[i] = flat[r]
    return ids, n


@numba.njit(nogil=True, cache=True, boundscheck=False)
def _accumulate(lab, ids, n, probs, heat, gt, with_gt):
    """Per segment: pixels, boundary pixels, heat sums (all, interior, boundary), probability
    sums, class, row and column sums, pixels of its class in ``gt``; and the boundary pixels."""
    h, w = lab.shape
    nc, nh = probs.shape[0], heat.shape[0]
    count = np.zeros(n, np.int64)
    bd = np.zeros(n, np.int64)
    heat_all = np.zeros((n, nh))
    heat_in = np.zeros((n, nh))
    heat_bd = np.zeros((n, nh))
    prob = np.zeros((n, nc))
    cls = np.zeros(n)
    rows = np.zeros(n)
    cols = np.zeros(n)
    inter = np.zeros(n)
    edges = np.zeros((h, w), np.bool_)
    for y in range(h):
        y0, y1 = max(y - 1, 0), min(y + 2, h)
        for x in range(w):
            s = ids[y, x] - 1
            if s < 0:
                continue
            v = lab[y, x]
            x0, x1 = max(x - 1, 0), min(x + 2, w)
            edge = False
            for yy in range(y0, y1):
                for xx in range(x0, x1):
                    if lab[yy, xx] != v:
                        edge = True
            edges[y, x] = edge
            count[s] += 1
            cls[s] = v
            rows[s] += y
            cols[s] += x
            if edge:
                bd[s] += 1
            for m in range(nh):
                t = heat[m, y, x]
                heat_all[s, m] += t
                if edge:
                    heat_bd[s, m] += t
                else:
                    heat_in[s, m] += t
            for k in range(nc):  # per pixel: the classes' sums are independent chains
                prob[s, k] += probs[k, y, x]
            if with_gt and gt[y, x] == v:
                inter[s] += 1
    return count, bd, heat_all, heat_in, heat_bd, prob, cls, rows, cols, inter, edges


@numba.njit(nogil=True, cache=True, boundscheck=False)
def _union(lab, ids, count, edges, missed, m_ids, sizes):
    """The adjusted IoU's union per segment: its size plus the ``sizes`` of the components
    ``m_ids`` of ``missed`` (the ground truth's class where the label differs, else 255) of its
    class next to one of its pixels, each counted once. Such a pixel has another label: only
    boundary pixels (``edges``) have one next to them."""
    h, w = lab.shape
    m1 = sizes.size
    mark = np.full(m1, -1, np.int64)  # the last segment that met each component: fewer repeats
    pairs = np.empty(1024, np.int64)  # segment * m1 + component, repeats included
    n_pairs = 0
    for y in range(h):
        y0, y1 = max(y - 1, 0), min(y + 2, h)
        for x in range(w):
            if not edges[y, x]:
                continue
            s, v = ids[y, x] - 1, lab[y, x]
            x0, x1 = max(x - 1, 0), min(x + 2, w)
            for yy in range(y0, y1):
                for xx in range(x0, x1):
                    if missed[yy, xx] != v:
                        continue
                    j = m_ids[yy, xx]
                    if mark[j] == s:
                        continue
                    mark[j] = s
                    if n_pairs == pairs.size:
                        grown = np.empty(2 * pairs.size, np.int64)
                        grown[:n_pairs] = pairs
                        pairs = grown
                    pairs[n_pairs] = s * m1 + j
                    n_pairs += 1
    union = count.astype(np.float64)
    keys = np.sort(pairs[:n_pairs])
    for i in range(n_pairs):
        if i == 0 or keys[i] != keys[i - 1]:
            union[keys[i] // m1] += sizes[keys[i] % m1]
    return union
