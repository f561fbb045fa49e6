"""Per image, rule and class: pixels and 8-connected segments, per RoI where priors exist; per
image and rule the deferred pixels.

A segment belongs to the RoI holding most of its pixels (ties: the lowest id), as in the
segment metrics (docs/definitions.md §4); RoI 0 is the whole image.
"""

from __future__ import annotations

import numpy as np

from costseg.classes import CLASS_NAMES, ROI_NAMES
from costseg.decision.label_maps import DEFERRED
from costseg.metrics.functional.segments import label_segments, roi_totals

NUM_ROIS = len(ROI_NAMES) - 1


def label_counts(labels: np.ndarray, roi: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """Pixels and segments of every class in one label map.

    Args:
        labels: (H, W) train ids.
        roi: (H, W) RoI ids 1..4, or None (then only the whole image, RoI 0).

    Returns:
        pixels, segments: (N, R) int64 with R = 5 RoIs (0 = whole image), or (N, 1) without
        ``roi``.

    >>> p, s = label_counts(np.array([[0, 0, 1], [1, 0, 0]]), None)
    >>> p[:2, 0].tolist(), s[:2, 0].tolist()
    ([4, 2], [1, 2])
    """
    n, rois = len(CLASS_NAMES), 1 if roi is None else NUM_ROIS + 1
    pixels = np.zeros((n, rois), dtype=np.int64)
    segments = np.zeros((n, rois), dtype=np.int64)
    flat = labels.ravel().astype(np.int64)
    if roi is None:
        pixels[:, 0] = np.bincount(flat, minlength=256)[:n]
    else:
        joint = np.bincount(flat * rois + roi.ravel(), minlength=256 * rois)[: n * rois]
        pixels[:] = joint.reshape(n, rois)
        pixels[:, 0] = pixels[:, 1:].sum(1)
    for c in np.flatnonzero(pixels[:, 0]):
        found = label_segments(labels == c, roi, NUM_ROIS)
        segments[c] = roi_totals(found.owner[1:], NUM_ROIS)[:rois]
    return pixels, segments


def deferred_pixels(labels: np.ndarray, roi: np.ndarray | None) -> np.ndarray:
    """Deferred pixels (label 255, docs/definitions.md §14) of one label map.

    Args:
        labels: (H, W) train ids, 255 where the rule deferred.
        roi: (H, W) RoI ids 1..4, or None.

    Returns:
        (R,) int64 with R = 5 RoIs (0 = whole image), or (1,) without ``roi``.

    >>> deferred_pixels(np.array([[255, 0], [255, 255]]), np.array([[1, 1], [2, 1]])).tolist()
    [3, 2, 1, 0, 0]
    """
    deferred = labels.ravel() == DEFERRED
    if roi is None:
        return np.array([np.count_nonzero(deferred)], dtype=np.int64)
    counts = np.bincount(roi.ravel()[deferred].astype(np.int64), minlength=NUM_ROIS + 1)
    counts[0] = counts[1:].sum()
    return counts[: NUM_ROIS + 1].astype(np.int64)
