"""Per-image counts and losses of one guarantee target, for K decision rules at once
(docs/definitions.md §7).

Learn-then-Test needs a loss ``L_i(λ)`` per image i and rule λ. For a class ``cls`` in a RoI
these come from per-image counts (numerator, denominator):

* ``recall``: (TP, TP + FN) pixels of ``cls`` inside the RoI (a deferred pixel is a miss);
  loss ``1 − recall``;
* ``precision``: (TP, TP + FP) pixels of ``cls`` inside the RoI; loss ``1 − precision``;
* ``coverage``, ``selective_recall``, ``handled_recall`` (docs/definitions.md §14; D: the
  pixels of ``cls`` deferred, G: all of them): (G − D, G), (TP, G − D), (TP + D, G); loss
  1 − the metric; ``cls`` None: the coverage over all classes (G: every counted pixel);
* ``fn_rate``: (FN segments, ground-truth segments) of ``cls`` owned by the RoI; loss the rate;
* ``fp_rate``: (FP segments, predicted segments) of ``cls`` owned by the RoI; loss the rate;
* ``instance_recall``: (instances found, instances) of ``cls`` owned by the RoI; loss the
  fraction of the image's instances missed (``docs/definitions.md §9``).

Pixel counts come from :func:`~costseg.metrics.functional.roi_confusion` (ignored pixels count
nowhere) and segment counts from the segment counter of :class:`~costseg.metrics.SegmentErrors`
(8-connected components, owner = the RoI holding most pixels), so summing the counts over images
gives exactly the pooled metrics' counts. RoI id 0 means the whole image.

>>> preds = torch.tensor([[[[1, 1], [0, 0]], [[1, 0], [0, 0]]]])     # (B=1, K=2, 2, 2)
>>> target = torch.tensor([[[1, 1], [1, 255]]])
>>> per_image_counts(preds, target, None, cls=1, roi_id=0, metric="recall").tolist()
[[[2, 3], [1, 3]]]
>>> per_image_loss(torch.tensor([[[2, 4], [0, 0]]]), "recall").tolist()
[[0.5, nan]]
"""

from __future__ import annotations

import numpy as np
import torch
from numpy.typing import ArrayLike
from torch import Tensor

from costseg.classes import IGNORE_INDEX, NUM_CLASSES, NUM_ROIS
from costseg.decision.label_maps import DEFERRED
from costseg.metrics.functional.inputs import check_batch
from costseg.metrics.functional.instances import instance_misses
from costseg.metrics.functional.roi import roi_confusion
from costseg.metrics.functional.segment_rules import packed_masks, rule_errors
from costseg.metrics.names import (
    DEFER_RATE_PARTS,
    DEFER_RATES,
    HIGHER_IS_BETTER,
    INSTANCE_RATES,
    PIXEL_RATE_PARTS,
    PIXEL_RATES,
    SEGMENT_COUNTS,
    SEGMENT_RATE_PARTS,
    TARGET_METRICS,
)

__all__ = ["per_image_counts", "per_image_loss", "pixel_parts"]


def per_image_counts(
    preds: Tensor,
    target: Tensor,
    roi: Tensor | None,
    cls: int | None,
    roi_id: int,
    metric: str,
    num_rois: int = NUM_ROIS,
    ignore_index: int = IGNORE_INDEX,
    instances: Tensor | None = None,
) -> Tensor:
    """Per image and rule, the (numerator, denominator) counts behind ``metric``.

    Args:
        preds: (B, K, H, W) integer class ids of K rules (any integer dtype, e.g. uint8), or
            ``DEFERRED``.
        target: (B, H, W) integer class ids, or ``ignore_index``.
        roi: None, (H, W) or (B, H, W) RoI ids in 0..num_rois (0 = in no RoI).
        cls: the class; None: every class (``coverage`` only, ``all:roi:coverage``).
        roi_id: the RoI (0 = whole image; an id >= 1 needs ``roi``).
        metric: one of :data:`~costseg.metrics.names.TARGET_METRICS` (see the module docstring).
        num_rois: R.
        ignore_index: target value that counts nowhere.
        instances: (B, H, W) instance ids (Cityscapes' encoding), for "instance_recall".

    Returns:
        int64 (B, K, 2) on preds' device: ``[..., 0]`` the numerator, ``[..., 1]`` the
        denominator (0 where the loss is undefined).

    >>> preds = torch.tensor([[[[1, 0, 0, 1], [0, 1, 0, 0]]]])          # (1, 1, 2, 4)
    >>> target = torch.tensor([[[0, 0, 0, 1], [0, 0, 1, 1]]])
    >>> per_image_counts(preds, target, None, 1, 0, "fp_rate").tolist()  # 1 of 2 segments
    [[[1, 2]]]
    """
    _check_args(preds, target, roi, cls, roi_id, metric, num_rois, ignore_index)
    if metric in (*PIXEL_RATES, *DEFER_RATES):
        return _pixel_counts(preds, target, roi, cls, roi_id, metric, num_rois, ignore_index)
    if metric in INSTANCE_RATES:
        if instances is None:
            raise ValueError("instance_recall needs instance ids, and these images have none")
        out = instance_misses(preds, target, instances, (cls,), roi, num_rois, ignore_index)
        whole = out.gt[:, 0, :, roi_id].sum(-1, keepdim=True).expand(-1, preds.shape[1])
        found = whole - out.missed[:, :, 0, :, roi_id].sum(-1)
        return torch.stack([found, whole], -1)
    return _segment_counts(preds, target, roi, cls, roi_id, metric, num_rois, ignore_index)


def _check_args(
    preds: Tensor,
    target: Tensor,
    roi: Tensor | None,
    cls: int | None,
    roi_id: int,
    metric: str,
    num_rois: int,
    ignore_index: int,
) -> None:
    """Raise ValueError unless the inputs fit :func:`per_image_counts`."""
    if not isinstance(preds, Tensor) or preds.ndim != 4:
        got = f"shape {tuple(preds.shape)}" if isinstance(preds, Tensor) else type(preds).__name__
        raise ValueError(f"expected preds as an integer (B, K, H, W) tensor, got {got}")
    check_batch(preds, target, roi, num_rois)
    if metric not in TARGET_METRICS:
        raise ValueError(f"metric must be one of {', '.join(TARGET_METRICS)}; got {metric!r}")
    if cls is None and metric != "coverage":
        raise ValueError(f"over all classes (cls None) only coverage is measured, not {metric}")
    if cls is not None and (cls < 0 or cls == ignore_index):
        raise ValueError(f"expected cls >= 0 and != ignore_index {ignore_index}, got {cls}")
    if not 0 <= roi_id <= num_rois:
        raise ValueError(f"expected roi_id in 0..{num_rois}, got {roi_id}")
    if roi_id > 0 and roi is None:
        raise ValueError(f"roi_id {roi_id} needs a RoI map; got roi=None")


def _pixel_counts(
    preds: Tensor,
    target: Tensor,
    roi: Tensor | None,
    cls: int | None,
    roi_id: int,
    metric: str,
    num_rois: int,
    ignore_index: int,
) -> Tensor:
    """(B, K, 2): the (numerator, denominator) pixels of ``metric`` (the module docstring) of
    ``cls`` in RoI ``roi_id``, from each image's confusion counts (deferred pixels in the last
    column)."""
    out = []
    for b in range(len(target)):
        image_roi = roi if roi is None or roi.ndim == 2 else roi[b]
        cm = roi_confusion(
            preds[b : b + 1], target[b : b + 1], image_roi, NUM_CLASSES, num_rois, ignore_index,
            DEFERRED,
        )  # fmt: skip
        out.append(pixel_parts(cm[:, roi_id], cls, metric))
    return torch.stack(out)


def pixel_parts(confusion: Tensor, cls: int | None, metric: str) -> Tensor:
    """The (numerator, denominator) pixels of a pixel rate or a rate of deferral (the module
    docstring) of ``cls`` (None: every class, ``coverage``) from confusion counts.

    Args:
        confusion: (..., N, N + 1) counts of one RoI, true class × decision (the deferred pixels
            in the last column), as :func:`~costseg.metrics.functional.roi_confusion` gives.
        cls, metric: as for :func:`per_image_counts`.

    Returns:
        (..., 2) counts.

    >>> cm = torch.tensor([[3, 1, 1], [2, 4, 0]])          # 2 classes; column 2: deferred
    >>> pixel_parts(cm, 0, "recall").tolist(), pixel_parts(cm, 0, "handled_recall").tolist()
    ([3, 5], [4, 5])
    """
    n = confusion.shape[-2]
    if cls is None:  # all:roi:coverage, over every class
        gt, deferred = confusion.sum((-2, -1)), confusion[..., n].sum(-1)
        tp = predicted = torch.zeros_like(gt)
    else:
        tp, predicted = confusion[..., cls, cls], confusion[..., :, cls].sum(-1)
        gt, deferred = confusion[..., cls, :].sum(-1), confusion[..., cls, n]
    if metric in PIXEL_RATE_PARTS:  # a deferred pixel is a false negative
        parts = PIXEL_RATE_PARTS[metric](tp, predicted - tp, gt - tp)
    else:
        parts = DEFER_RATE_PARTS[metric](tp, gt - deferred, deferred)
    return torch.stack(parts, -1)


def _segment_counts(
    preds: Tensor,
    target: Tensor,
    roi: Tensor | None,
    cls: int,
    roi_id: int,
    metric: str,
    num_rois: int,
    ignore_index: int,
) -> Tensor:
    """(B, K, 2): (FN, GT) or (FP, predicted) segments of ``cls`` owned by RoI ``roi_id``."""
    rows = [SEGMENT_COUNTS.index(name) for name in SEGMENT_RATE_PARTS[metric]]
    pred_masks = packed_masks(preds, cls, target != ignore_index)
    gt_masks = (target == cls).cpu().numpy()
    rois = None if roi is None else roi.expand_as(target).cpu().numpy()
    out = np.zeros((*preds.shape[:2], 2), dtype=np.int64)
    for b in range(len(target)):
        # The segment core of SegmentErrors: one labelling per distinct mask of the K rules.
        errors = rule_errors(
            pred_masks[b], gt_masks[b], None if rois is None else rois[b], num_rois, maps=False
        )
        out[b] = errors.counts[errors.inverse][:, rows, roi_id]
    return torch.from_numpy(out).to(preds.device)


def per_image_loss(counts: ArrayLike | Tensor, metric: str) -> Tensor:
    """Per-image losses in [0, 1] from :func:`per_image_counts`; NaN where undefined.

    Args:
        counts: (n, K, 2) (numerator, denominator) counts.
        metric: the metric the counts were taken for: the loss is 1 − the metric (recall,
            precision, instance recall, the rates of deferral), or the FN- or FP-segment rate.

    Returns:
        float64 (n, K) losses, NaN where the denominator is 0.

    >>> per_image_loss(torch.tensor([[[3, 4]], [[0, 0]]]), "precision").tolist()
    [[0.25], [nan]]
    >>> per_image_loss(torch.tensor([[[1, 4]]]), "fn_rate").tolist()
    [[0.25]]
    """
    counts = torch.as_tensor(counts)
    if counts.ndim != 3 or counts.shape[-1] != 2:
        raise ValueError(f"expected (n, K, 2) counts, got shape {tuple(counts.shape)}")
    if metric not in TARGET_METRICS:
        raise ValueError(f"metric must be one of {', '.join(TARGET_METRICS)}; got {metric!r}")
    part, whole = counts.double().unbind(-1)
    if bool((part < 0).any() | (part > whole).any()):
        raise ValueError(f"{metric}: expected counts 0 <= numerator <= denominator")
    if metric in HIGHER_IS_BETTER:  # the loss is 1 − part / whole; the segment rates are losses
        part = whole - part
    return torch.where(whole > 0, part / whole.clamp(min=1), torch.nan)
