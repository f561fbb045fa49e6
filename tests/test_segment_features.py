"""MetaSeg segment features of costseg.meta.features against a plain-Python reference (flood
fills, neighbour checks and means written from the definitions) and hand-computed cases."""

from __future__ import annotations

import warnings
from collections import deque

import numpy as np
import pytest

from costseg.meta.features import (
    FEATURES_OF_SIZE,
    HEAT_SUFFIXES,
    TARGETS,
    SegmentTable,
    feature_names,
    segment_features,
)


def neighbours(y: int, x: int, h: int, w: int) -> list[tuple[int, int]]:
    """The 8 neighbours of (y, x) inside an (h, w) image."""
    return [
        (y + dy, x + dx)
        for dy in (-1, 0, 1)
        for dx in (-1, 0, 1)
        if (dy or dx) and 0 <= y + dy < h and 0 <= x + dx < w
    ]


def flood(start: tuple[int, int], inside, h: int, w: int) -> list[tuple[int, int]]:
    """The pixels reached from ``start`` through 8-neighbours for which ``inside`` holds."""
    seen, queue, order = {start}, deque([start]), []
    while queue:
        p = queue.popleft()
        order.append(p)
        for q in neighbours(*p, h, w):
            if q not in seen and inside(q):
                seen.add(q)
                queue.append(q)
    return order


def reference(labels, probs, heat, gt=None) -> tuple[np.ndarray, dict[str, list[float]]]:
    """The segment ids and feature columns (and targets), from the definitions."""
    h, w = labels.shape
    lab = [[int(v) for v in row] for row in labels]
    if gt is not None:
        lab = [[255 if gt[y, x] == 255 else lab[y][x] for x in range(w)] for y in range(h)]
    ids = np.zeros((h, w), np.int32)
    segments = []
    for y in range(h):  # row-major: a segment's number from its first pixel
        for x in range(w):
            if lab[y][x] == 255 or ids[y, x]:
                continue
            c = lab[y][x]
            pixels = flood((y, x), lambda q, c=c: lab[q[0]][q[1]] == c, h, w)
            segments.append((c, pixels))
            for p in pixels:
                ids[p] = len(segments)
    cols: dict[str, list[float]] = {}

    def put(name, value):
        cols.setdefault(name, []).append(float(value))

    def mean(values):
        return sum(values) / len(values) if values else 0.0

    for c, pixels in segments:
        bd = [p for p in pixels if any(lab[q[0]][q[1]] != c for q in neighbours(*p, h, w))]
        inner = [p for p in pixels if p not in set(bd)]
        s, s_in, s_bd = len(pixels), len(inner), len(bd)
        s_rel, s_rel_in = s / (s_bd or 1), s_in / (s_bd or 1)
        for name, value in zip(FEATURES_OF_SIZE, (s, s_in, s_bd, s_rel, s_rel_in), strict=True):
            put(name, value)
        for name, m in heat.items():
            e = mean([float(m[p]) for p in pixels])
            e_in = mean([float(m[p]) for p in inner])
            e_bd = mean([float(m[p]) for p in bd])
            values = (e, e_in, e_bd, e * s_rel, e_in * s_rel_in)
            for suffix, value in zip(HEAT_SUFFIXES, values, strict=True):
                put(name + suffix, value)
        for k in range(len(probs)):
            put(f"cprob{k}", mean([float(probs[k][p]) for p in pixels]))
        put("class", c)
        put("row", mean([p[0] for p in pixels]))
        put("col", mean([p[1] for p in pixels]))
        if gt is None:
            continue
        inter = sum(int(gt[p]) == c for p in pixels)

        def missed(q, c=c):
            return int(gt[q]) == c and lab[q[0]][q[1]] != c

        reached: set[tuple[int, int]] = set()
        for p in pixels:  # every missed component next to the segment, once
            for q in neighbours(*p, h, w):
                if missed(q) and q not in reached:
                    reached.update(flood(q, missed, h, w))
        put("iou", inter / (s + len(reached)))
        put("iou0", inter == 0)
    return ids, cols


def check(labels, probs, heat, gt=None) -> SegmentTable:
    """segment_features equals the reference: ids exactly, every column to rounding."""
    table = segment_features(labels, probs, heat, gt)
    ids, cols = reference(labels, probs, heat, gt)
    np.testing.assert_array_equal(table.ids, ids)
    assert table.ids.dtype == np.int32
    expected = feature_names(list(heat), len(probs)) + (list(TARGETS) if gt is not None else [])
    assert list(table.columns) == expected
    assert table.count == ids.max()
    for name in expected:
        column = table.columns[name]
        assert column.dtype == np.float64 and column.shape == (table.count,), name
        np.testing.assert_allclose(column, cols.get(name, []), rtol=1e-12, atol=0, err_msg=name)
    return table


def uniform(num_classes: int, shape: tuple[int, int]) -> np.ndarray:
    return np.full((num_classes, *shape), 1 / num_classes, np.float32)


def test_feature_names():
    assert feature_names(["E", "D"], 2) == [
        *("S", "S_in", "S_bd", "S_rel", "S_rel_in"),
        *("E", "E_in", "E_bd", "E_rel", "E_rel_in"),
        *("D", "D_in", "D_bd", "D_rel", "D_rel_in"),
        *("cprob0", "cprob1", "class", "row", "col"),
    ]


def test_block_in_a_ring():
    """A 3x3 block of class 1 in a 5x5 map of class 0: the block's centre is its only interior
    pixel (S=9, S_in=1, S_bd=8); every pixel of the class-0 ring touches the block, the corners
    (0, 0) included (diagonal (1, 1)): S=16, S_in=0, S_bd=16. Segment 1 is the ring ((0, 0))."""
    labels = np.zeros((5, 5), np.uint8)
    labels[1:4, 1:4] = 1
    rows = np.repeat(np.arange(5, dtype=np.float32), 5).reshape(5, 5)
    table = check(labels, uniform(2, (5, 5)), {"E": rows})
    c = table.columns
    assert c["S"].tolist() == [16, 9] and c["S_in"].tolist() == [0, 1]
    assert c["S_bd"].tolist() == [16, 8]
    assert c["S_rel"].tolist() == [1, 9 / 8] and c["S_rel_in"].tolist() == [0, 1 / 8]
    assert c["class"].tolist() == [0, 1]
    assert c["row"].tolist() == [2, 2] and c["col"].tolist() == [2, 2]
    # E = the row index: the block's mean, interior (2, 2) and boundary means are all 2
    assert c["E"].tolist() == [2, 2] and c["E_in"].tolist() == [0, 2]
    assert c["E_bd"].tolist() == [2, 2] and c["E_rel"].tolist() == [2, 2 * 9 / 8]
    assert c["E_rel_in"].tolist() == [0, 2 / 8]
    assert c["cprob0"].tolist() == [0.5, 0.5]


def test_wide_ring_has_interior_at_the_edge():
    """The block in a 7x7 map: the 24 pixels on the image's edge touch only class 0 (interior:
    the edge makes no boundary), the 16 next to the block are boundary: S=40, S_in=24."""
    labels = np.zeros((7, 7), np.int64)
    labels[2:5, 2:5] = 1
    c = check(labels, uniform(2, (7, 7)), {}).columns
    assert c["S"].tolist() == [40, 9] and c["S_in"].tolist() == [24, 1]
    assert c["S_bd"].tolist() == [16, 8] and c["S_rel_in"].tolist() == [24 / 16, 1 / 8]


def test_segment_touching_the_edge():
    """Two halves of a 4x6 map: each half's boundary is only its column next to the other."""
    labels = np.zeros((4, 6), np.uint8)
    labels[:, 3:] = 1
    heat = {"E": np.tile(np.arange(6, dtype=np.float32), (4, 1))}  # the column index
    c = check(labels, uniform(2, (4, 6)), heat).columns
    assert c["S"].tolist() == [12, 12] and c["S_in"].tolist() == [8, 8]
    assert c["S_bd"].tolist() == [4, 4]
    assert c["E_bd"].tolist() == [2, 3] and c["E_in"].tolist() == [0.5, 4.5]
    assert c["col"].tolist() == [1, 4] and c["row"].tolist() == [1.5, 1.5]


def test_diagonal_pixels_and_numbering():
    """Class 3 at (0, 0) and (1, 1) is one segment (8-connected), as are the class-0 pixels
    (0, 1), (0, 2), (1, 0) and the class-1 pixels (1, 2), (2, 0), (2, 1); (2, 2) of class 0 is
    apart. Numbered by first pixel over all classes: (0, 0), (0, 1), (1, 2), (2, 2)."""
    labels = np.array([[3, 0, 0], [0, 3, 1], [1, 1, 0]], np.uint8)
    table = check(labels, uniform(4, (3, 3)), {})
    assert table.ids.tolist() == [[1, 2, 2], [2, 1, 3], [3, 3, 4]]
    assert table.columns["class"].tolist() == [3, 0, 1, 0]
    assert table.columns["S"].tolist() == [2, 3, 3, 1]


def test_ignored_and_deferred_pixels():
    """gt 255 at (1, 1) masks its label (here class 2: no class-2 segment is left); the eight
    class-0 pixels around it are boundary, the last column interior: S=11, S_in=3, S_bd=8."""
    labels = np.zeros((3, 4), np.uint8)
    labels[1, 1] = 2
    gt = np.zeros((3, 4), np.uint8)
    gt[1, 1] = 255
    table = check(labels, uniform(3, (3, 4)), {}, gt)
    assert table.ids[1, 1] == 0 and table.count == 1
    c = table.columns
    assert c["S"].tolist() == [11] and c["S_in"].tolist() == [3] and c["S_bd"].tolist() == [8]
    assert c["iou"].tolist() == [1.0] and c["iou0"].tolist() == [0.0]
    # a column of label 255 (deferred) splits class 1 in two segments, all boundary
    labels = np.array([[1, 255, 1], [1, 255, 1]], np.uint8)
    table = check(labels, uniform(2, (2, 3)), {})
    assert table.ids.tolist() == [[1, 0, 2], [1, 0, 2]]
    assert table.columns["S_bd"].tolist() == [2, 2] and table.columns["S_in"].tolist() == [0, 0]


def test_adjusted_iou_of_a_split_object():
    """The gt object of class 1 on rows 0-1 is predicted as two class-1 segments with class 0
    between: the missed part (rows 0-1, columns 2-4: 6 pixels) widens each segment's union, the
    other segment's 4 pixels do not: iou = 4 / (4 + 6). The class-0 segment (rows 0-1 columns
    2-4 and row 2: 13 pixels) has 7 of gt 0 and nothing missed: 7 / 13."""
    labels = np.zeros((3, 7), np.uint8)
    labels[:2, :2] = labels[:2, 5:] = 1
    gt = np.zeros((3, 7), np.uint8)
    gt[:2] = 1
    table = check(labels, uniform(2, (3, 7)), {}, gt)
    assert table.columns["class"].tolist() == [1, 0, 1]
    assert table.columns["iou"].tolist() == [0.4, 7 / 13, 0.4]
    assert table.columns["iou0"].tolist() == [0, 0, 0]
    # gt 1 at (2, 3) joins the missed component through (1, 3): 4 / (4 + 7); gt 1 at (3, 0) is
    # a missed component of its own, not next to the class-1 segments: it does not count
    labels = np.zeros((4, 7), np.uint8)
    labels[:2, :2] = labels[:2, 5:] = 1
    gt = np.zeros((4, 7), np.uint8)
    gt[:2] = gt[2, 3] = gt[3, 0] = 1
    table = check(labels, uniform(2, (4, 7)), {}, gt)
    assert table.columns["iou"].tolist() == [4 / 11, 12 / 20, 4 / 11]


def test_missed_pixels_predicted_255_widen_the_union():
    """A deferred pixel (label 255) of gt class 1 next to the class-1 segment is missed: 2/3."""
    labels = np.array([[1, 1, 255]], np.uint8)
    gt = np.array([[1, 1, 1]], np.uint8)
    table = check(labels, uniform(2, (1, 3)), {}, gt)
    assert table.columns["iou"].tolist() == [2 / 3]


def test_false_positive():
    """A class-2 segment where the ground truth has no class 2: iou0 = 1, iou = 0."""
    labels = np.zeros((4, 4), np.uint8)
    labels[1:3, 1:3] = 2
    gt = np.zeros((4, 4), np.uint8)
    c = check(labels, uniform(3, (4, 4)), {}, gt).columns
    assert c["iou0"].tolist() == [0, 1] and c["iou"].tolist() == [12 / 16, 0]


def softmax(logits: np.ndarray) -> np.ndarray:
    e = np.exp(logits - logits.max(0))
    return (e / e.sum(0)).astype(np.float32)


@pytest.mark.parametrize("seed", range(8))
def test_random_maps_equal_the_reference(seed: int):
    rng = np.random.default_rng(seed)
    shape, n = (12, 17), int(rng.integers(3, 5))
    labels = rng.integers(0, n, shape)
    if seed % 2:  # blobs: larger segments with interiors
        labels = np.kron(rng.integers(0, n, (4, 6)), np.ones((3, 3), np.int64))[:12, :17]
        labels[rng.random(shape) < 0.15] = rng.integers(0, n)
    labels[rng.random(shape) < 0.05] = 255
    gt = np.where(rng.random(shape) < 0.7, labels, rng.integers(0, n, shape))
    gt[gt == 255] = 0
    gt[rng.random(shape) < 0.08] = 255
    probs = softmax(rng.normal(size=(n, *shape)) * 3)
    heat = {k: rng.random(shape, dtype=np.float32) for k in ("E", "D", "R", "MI")}
    dtype = np.uint8 if seed < 4 else np.int64
    check(labels.astype(dtype), probs, heat, gt.astype(dtype))
    check(labels.astype(dtype), probs, heat)


def test_input_types_give_the_same_table():
    rng = np.random.default_rng(11)
    labels = rng.integers(0, 3, (6, 9)).astype(np.uint8)
    probs = softmax(rng.normal(size=(3, 9, 6))).transpose(0, 2, 1)  # not contiguous
    heat = {"E": rng.random((6, 9)).astype(np.float32)}
    a = segment_features(labels, probs, heat, labels)
    b = segment_features(labels.astype(np.int64), probs.copy(), heat, labels.astype(np.int64))
    np.testing.assert_array_equal(a.ids, b.ids)
    assert a.columns.keys() == b.columns.keys()
    for name in a.columns:
        np.testing.assert_array_equal(a.columns[name], b.columns[name])


def test_single_label_map_has_no_boundary():
    """One label everywhere: S_bd = 0, S_rel = S / 1, boundary means 0, no division warning."""
    labels = np.ones((4, 5), np.uint8)
    heat = {"E": np.arange(20, dtype=np.float32).reshape(4, 5)}
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        c = check(labels, uniform(2, (4, 5)), heat, labels).columns
    assert c["S_bd"].tolist() == [0] and c["S_rel"].tolist() == [20]
    assert c["S_rel_in"].tolist() == [20] and c["E_bd"].tolist() == [0]
    assert c["E_in"].tolist() == [9.5] and c["E_rel_in"].tolist() == [9.5 * 20]
    assert c["iou"].tolist() == [1]


def test_no_segment_at_all():
    labels = np.full((3, 3), 255, np.uint8)
    table = segment_features(labels, uniform(2, (3, 3)), {"E": np.zeros((3, 3), np.float32)})
    assert table.count == 0 and not table.ids.any()
    assert all(len(column) == 0 for column in table.columns.values())
