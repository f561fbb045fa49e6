"""Segment-wise errors of one class (docs/definitions.md §4): 8-connected components of the
predicted and ground-truth masks, and which of them the other mask misses.

A predicted segment of class c is a false positive when it holds no pixel with target c; a
ground-truth segment is a false negative when it holds no pixel predicted c. A segment belongs to
the RoI holding most of its pixels (ties: lowest id). A deferred pixel (label 255,
docs/definitions.md §14) is predicted as no class: it lies in no predicted segment, and it does
not keep a ground-truth segment from being a false negative. :func:`segment_errors` is the
definition on one image; :func:`mask_segment_errors` its core, shared with :mod:`.segment_rules`
(K rules).

>>> pred = torch.tensor([[1, 0, 0, 1], [0, 1, 0, 0]])   # a diagonal pair is ONE segment
>>> segment_errors(pred, torch.tensor([[0, 0, 0, 1], [0, 0, 1, 1]]), cls=1)["fp"]
1
"""

from __future__ import annotations

from typing import Any, NamedTuple

import numpy as np
import torch
from scipy import ndimage
from torch import Tensor

from costseg.classes import IGNORE_INDEX, NUM_ROIS
from costseg.metrics.functional.inputs import check_batch, describe
from costseg.metrics.names import SEGMENT_COUNTS

EIGHT_CONNECTED = np.ones((3, 3), dtype=bool)
"""The structure of ``scipy.ndimage.label`` that makes diagonal neighbours one segment."""


class Segments(NamedTuple):
    """The 8-connected components of one (H, W) mask."""

    labels: np.ndarray  # (H, W) component id per pixel, 0 = background
    count: int
    owner: np.ndarray  # (count + 1,) RoI id holding most pixels of each component (0 if no roi)


def label_segments(mask: np.ndarray, roi: np.ndarray | None, num_rois: int) -> Segments:
    """Label the 8-connected components of a (H, W) bool mask and find each one's RoI."""
    labels, count = ndimage.label(mask, structure=EIGHT_CONNECTED)
    if roi is None:
        return Segments(labels, count, np.zeros(count + 1, dtype=np.int64))
    r1 = num_rois + 1
    votes = np.bincount(labels[mask] * r1 + roi[mask], minlength=(count + 1) * r1)
    # argmax takes the first maximum, so ties go to the lowest RoI id (docs/definitions.md §4).
    return Segments(labels, count, votes.reshape(count + 1, r1).argmax(1))


def missed_segments(segments: Segments, hits: np.ndarray) -> np.ndarray:
    """(count + 1,) bool: components holding no pixel of the (H, W) mask ``hits``; entry 0 False."""
    missed = np.bincount(segments.labels[hits], minlength=segments.count + 1) == 0
    missed[0] = False
    return missed


def roi_totals(owner: np.ndarray, num_rois: int) -> np.ndarray:
    """(R+1,) int64 number of components per owning RoI, index 0 replaced by the total."""
    counts = np.bincount(owner, minlength=num_rois + 1)
    counts[0] = len(owner)
    return counts


def segment_errors(
    pred: Tensor,
    target: Tensor,
    cls: int = 11,
    ignore_index: int = IGNORE_INDEX,
    roi: Tensor | None = None,
    num_rois: int = NUM_ROIS,
) -> dict[str, Any]:
    """False-positive and false-negative 8-connected segments of one class in one image.

    A predicted segment (component of ``pred == cls`` on non-ignored pixels) is a false positive
    when it holds no pixel with ``target == cls``; a ground-truth segment (component of
    ``target == cls``) is a false negative when it holds no pixel with ``pred == cls``. A segment
    belongs to the RoI id holding most of its pixels (ties: lowest id; id 0 = in no RoI).

    Args:
        pred: (H, W) integer class ids.
        target: (H, W) integer class ids or ``ignore_index``.
        cls: the class.
        ignore_index: target value that is ignored.
        roi: None or (H, W) RoI ids in 0..num_rois.
        num_rois: R.

    Returns:
        ints "fp", "fn", "n_pred", "n_gt"; bool (H, W) "fp_mask", "fn_mask" (pixels of the FP /
        FN segments); with ``roi``, int64 (R+1,) "fp_roi", "fn_roi", "n_pred_roi", "n_gt_roi"
        (index 0 = whole image). Tensors are on pred's device.

    >>> pred = torch.tensor([[1, 0, 0, 1], [0, 1, 0, 0]])   # a diagonal pair is ONE segment
    >>> target = torch.tensor([[0, 0, 0, 1], [0, 0, 1, 1]])
    >>> out = segment_errors(pred, target, cls=1)
    >>> out["fp"], out["fn"], out["n_pred"], out["n_gt"]
    (1, 0, 2, 1)
    """
    if not (isinstance(pred, Tensor) and isinstance(target, Tensor)) or (
        pred.ndim != 2 or pred.shape != target.shape
    ):
        raise ValueError(
            "expected pred and target as (H, W) tensors of one shape, "
            f"got {describe(pred)} and {describe(target)}"
        )
    if roi is not None and (not isinstance(roi, Tensor) or roi.shape != pred.shape):
        raise ValueError(
            f"expected roi None or an integer {tuple(pred.shape)} tensor, got {describe(roi)}"
        )
    check_batch(pred[None], target[None], roi, num_rois)
    if cls < 0 or cls == ignore_index:
        raise ValueError(f"expected cls >= 0 and != ignore_index {ignore_index}, got {cls}")
    p, t = pred.cpu().numpy(), target.cpu().numpy()
    r = None if roi is None else roi.cpu().numpy()
    gt_mask = t == cls
    errors = mask_segment_errors((p == cls) & (t != ignore_index), gt_mask, r, num_rois)
    out: dict[str, Any] = {
        k: int(v) for k, v in zip(SEGMENT_COUNTS, errors.counts[:, 0], strict=True)
    }
    out["fp_mask"] = torch.from_numpy(errors.fp_mask).to(pred.device)
    out["fn_mask"] = torch.from_numpy(errors.fn_mask).to(pred.device)
    if roi is not None:
        for i, key in enumerate(SEGMENT_COUNTS):
            out[f"{key}_roi"] = torch.from_numpy(errors.counts[i]).to(pred.device)
    return out


class MaskErrors(NamedTuple):
    """Segment errors of one class's predicted mask against its ground truth."""

    counts: np.ndarray  # (4, R+1) int64: fp, fn, n_pred, n_gt; column 0 = whole image
    fp_mask: np.ndarray  # (H, W) bool, pixels of false-positive segments
    fn_mask: np.ndarray  # (H, W) bool, pixels of false-negative segments


def mask_segment_errors(
    pred_mask: np.ndarray,
    gt_mask: np.ndarray,
    roi: np.ndarray | None,
    num_rois: int,
    gt: Segments | None = None,
) -> MaskErrors:
    """The core of the segment errors (docs/definitions.md §4), shared by :func:`segment_errors` and
    :class:`~costseg.metrics.SegmentErrors`.

    Args:
        pred_mask: (H, W) bool, ``pred == cls`` on non-ignored pixels.
        gt_mask: (H, W) bool, ``target == cls`` (never ignored pixels).
        roi: None or (H, W) RoI ids in 0..num_rois.
        num_rois: R.
        gt: ``label_segments(gt_mask, roi, num_rois)`` when already known (it does not depend
            on the rule, so K rules label it once).
    """
    gt = label_segments(gt_mask, roi, num_rois) if gt is None else gt
    pred = label_segments(pred_mask, roi, num_rois)
    # Ground-truth pixels are never ignored, so pred_mask equals pred == cls on them.
    fp_seg, fn_seg = missed_segments(pred, gt_mask), missed_segments(gt, pred_mask)
    counts = np.stack(
        [
            roi_totals(pred.owner[fp_seg], num_rois),
            roi_totals(gt.owner[fn_seg], num_rois),
            roi_totals(pred.owner[1:], num_rois),
            roi_totals(gt.owner[1:], num_rois),
        ]
    )
    return MaskErrors(counts, fp_seg[pred.labels], fn_seg[gt.labels])
