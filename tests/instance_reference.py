"""A brute-force reference of the instance metrics (docs/definitions.md §9): one Python loop over
the instances of each image, shared by the instance tests."""

from __future__ import annotations

import numpy as np

from costseg.classes import LABEL_ID_TO_TRAIN_ID

SIZES = ("small", "medium", "large")


def reference_instances(
    preds: np.ndarray,
    target: np.ndarray,
    ids: np.ndarray,
    roi: np.ndarray | None,
    classes: tuple[int, ...],
    num_rois: int = 4,
) -> tuple[dict, dict, np.ndarray]:
    """Per image loop. preds (K, H, W), target (H, W), ids (H, W), roi (H, W) or None.

    Returns:
        gt[(cls, size, r)] and missed[(k, cls, size, r)] counts (r = 0: every instance) and the
        (K, C, H, W) bool pixels of missed instances.
    """
    h, w = target.shape
    scale = h * w / (1024 * 2048)
    gt: dict = {}
    missed: dict = {}
    masks = np.zeros((len(preds), len(classes), h, w), dtype=bool)
    for value in sorted(set(ids.ravel().tolist())):
        if value < 1000:
            continue  # stuff or crowd
        label_id = value // 1000
        cls = int(LABEL_ID_TO_TRAIN_ID[label_id]) if label_id < 256 else 255
        if cls not in classes:
            continue
        pixels = (ids == value) & (target != 255)
        area = int(pixels.sum())
        if area == 0:
            continue
        size = "small" if area < 1024 * scale else "medium" if area < 9216 * scale else "large"
        owner = 0
        if roi is not None:
            votes = [int((pixels & (roi == r)).sum()) for r in range(num_rois + 1)]
            owner = max(range(num_rois + 1), key=lambda r: (votes[r], -r))
        for r in {0, owner}:
            gt[cls, size, r] = gt.get((cls, size, r), 0) + 1
        for k, pred in enumerate(preds):
            if not (pred[pixels] == cls).any():
                for r in {0, owner}:
                    missed[k, cls, size, r] = missed.get((k, cls, size, r), 0) + 1
                masks[k, classes.index(cls)] |= pixels
    return gt, missed, masks
