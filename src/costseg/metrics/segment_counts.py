"""The counts of :func:`~costseg.metrics.functional.mask_segment_errors` in one compiled pass.

Once scipy has labelled the predicted mask's 8-connected components, one pass over the pixels
(numba) collects what numpy needs several boolean gathers and bincounts for: each component's
RoI votes, whether it holds a ground-truth pixel, and whether each ground-truth component holds
a predicted one. :class:`~costseg.metrics.SegmentErrors` uses it where no location maps are
wanted (a sweep: many masks per class and image).
"""

from __future__ import annotations

import numba
import numpy as np
from scipy import ndimage

from costseg.metrics.functional.segments import EIGHT_CONNECTED, Segments

_NO_ROI = np.zeros((1, 1), dtype=np.int64)


def mask_counts(
    pred_mask: np.ndarray, gt_mask: np.ndarray, roi: np.ndarray | None, num_rois: int, gt: Segments
) -> np.ndarray:
    """``mask_segment_errors(pred_mask, gt_mask, roi, num_rois, gt).counts``: (4, R+1) int64 fp,
    fn, n_pred, n_gt segments; column 0 = whole image."""
    labels, count = ndimage.label(pred_mask, structure=EIGHT_CONNECTED)
    roi = _NO_ROI if roi is None else roi
    return _counts(labels, count, gt_mask, gt.labels, gt.count, gt.owner, roi, num_rois + 1)


@numba.njit(nogil=True, cache=True, boundscheck=False)
def _counts(labels, count, gt_mask, gt_labels, gt_count, gt_owner, roi, r1):
    votes = np.zeros((count + 1, r1), np.int64)  # pixels of each component in each RoI
    pred_hit = np.zeros(count + 1, np.bool_)  # the component holds a ground-truth pixel
    gt_hit = np.zeros(gt_count + 1, np.bool_)  # the ground-truth component, a predicted one
    height, width = labels.shape
    with_roi = roi.shape == labels.shape  # _NO_ROI is (1, 1): a 1 x 1 image reads its 0 alike
    for i in range(height):
        for j in range(width):
            label = labels[i, j]
            if label:
                votes[label, roi[i, j] if with_roi else 0] += 1
                if gt_mask[i, j]:
                    pred_hit[label] = True
                    gt_hit[gt_labels[i, j]] = True
    component = np.ones(count + 1, np.bool_)
    component[0] = False  # the background
    return tally(votes, component, pred_hit, gt_owner, gt_hit)


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
