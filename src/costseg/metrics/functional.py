"""Pure functions behind the metrics (SPEC §4): RoI confusion counts and segment-wise errors.

Label maps hold train ids; pixels whose target is ``ignore_index`` count nowhere. RoI maps hold
ids 0..num_rois (0 = the location lies in no RoI); in every result, RoI index 0 is the whole
image and index r >= 1 the RoI with id r.

>>> preds = torch.tensor([[[0, 1], [1, 1]]])
>>> target = torch.tensor([[[0, 1], [0, 255]]])
>>> cm = roi_confusion(preds, target, num_classes=2, num_rois=0)
>>> cm[0].tolist()                                   # rows = target, columns = prediction
[[1, 1], [0, 1]]
>>> [p.tolist() for p in precision_recall(cm[0])]
[[1.0, 0.5], [0.5, 1.0]]
"""

from __future__ import annotations

from typing import Any, NamedTuple

import numpy as np
import torch
from scipy import ndimage
from torch import Tensor

from costseg.classes import IGNORE_INDEX, NUM_CLASSES

_EIGHT_CONNECTED = np.ones((3, 3), dtype=bool)
CONFUSION_CHUNK = 1 << 20  # rule x pixel entries indexed at once in roi_confusion


def _is_int(t: Tensor) -> bool:
    return not (t.is_floating_point() or t.is_complex() or t.dtype == torch.bool)


def check_batch(preds: Tensor, target: Tensor, roi: Tensor | None, num_rois: int) -> None:
    """Raise ValueError unless preds (B, [K,] H, W), target (B, H, W), roi (H, W)/(B, H, W) fit."""
    if not isinstance(preds, Tensor) or not _is_int(preds) or preds.ndim not in (3, 4):
        raise ValueError(
            f"expected preds as an integer (B, H, W) or (B, K, H, W) tensor, got {_desc(preds)}"
        )
    expected = (preds.shape[0], *preds.shape[-2:])
    if not isinstance(target, Tensor) or not _is_int(target) or tuple(target.shape) != expected:
        raise ValueError(f"expected target as an integer {expected} tensor, got {_desc(target)}")
    if roi is None:
        return
    if not isinstance(roi, Tensor) or not _is_int(roi) or roi.shape not in (expected, expected[1:]):
        raise ValueError(
            f"expected roi as an integer {expected} or {expected[1:]} tensor, got {_desc(roi)}"
        )
    lo, hi = (int(v) for v in torch.aminmax(roi)) if roi.numel() else (0, 0)
    if lo < 0 or hi > num_rois:
        raise ValueError(f"expected roi ids in 0..{num_rois}, got values in {lo}..{hi}")


def _desc(x: Any) -> str:
    return f"{x.dtype} tensor of shape {tuple(x.shape)}" if isinstance(x, Tensor) else repr(x)


def as_rules(preds: Tensor, num_rules: int) -> Tensor:
    """(B, K, H, W) view of preds; (B, H, W) is accepted when ``num_rules == 1``."""
    if isinstance(preds, Tensor) and preds.ndim == 3 and num_rules == 1:
        return preds.unsqueeze(1)
    if isinstance(preds, Tensor) and preds.ndim == 4 and preds.shape[1] == num_rules:
        return preds
    alternative = " or (B, H, W)" if num_rules == 1 else ""
    raise ValueError(
        f"expected preds of shape (B, {num_rules}, H, W){alternative}, got {_desc(preds)}"
    )


def roi_confusion(
    preds: Tensor,
    target: Tensor,
    roi: Tensor | None = None,
    num_classes: int = NUM_CLASSES,
    num_rois: int = 4,
    ignore_index: int = IGNORE_INDEX,
) -> Tensor:
    """Confusion matrices of the whole image and of each RoI, for one or K decision rules.

    Args:
        preds: (B, H, W) or (B, K, H, W) integer class ids in [0, num_classes).
        target: (B, H, W) integer class ids, or ``ignore_index``.
        roi: None, (H, W) or (B, H, W) RoI ids in 0..num_rois (0 = in no RoI).
        num_classes: N.
        num_rois: R.
        ignore_index: target value that counts nowhere.

    Returns:
        int64 (R+1, N, N), or (K, R+1, N, N) for 4-D preds, on preds' device:
        ``cm[..., r, t, p]`` = pixels with target t and prediction p in RoI r (r = 0: whole image).

    >>> roi = torch.tensor([[1, 0], [1, 1]])
    >>> cm = roi_confusion(torch.ones(1, 2, 2, dtype=torch.long), torch.eye(2).long()[None], roi,
    ...                    num_classes=2, num_rois=1)
    >>> cm.tolist()                                  # whole image, then RoI 1
    [[[0, 2], [0, 2]], [[0, 1], [0, 2]]]
    """
    check_batch(preds, target, roi, num_rois)
    lo, hi = (int(v) for v in torch.aminmax(preds)) if preds.numel() else (0, 0)
    if lo < 0 or hi >= num_classes:
        raise ValueError(f"expected preds in [0, {num_classes}), got values in {lo}..{hi}")
    bad = ((target < 0) | (target >= num_classes)) & (target != ignore_index)
    if bad.any():
        raise ValueError(
            f"expected target in [0, {num_classes}) or {ignore_index}, got {target[bad][0].item()}"
        )
    n, r1 = num_classes, num_rois + 1
    rules = preds if preds.ndim == 4 else preds.unsqueeze(1)
    # Ignored pixels land in an extra target row n, dropped below: no boolean indexing needed.
    rows = torch.where(target == ignore_index, n, target.long())
    if roi is not None:
        rows = rows + roi.long().expand_as(target) * (n + 1)
    per_rule = r1 * (n + 1) * n
    offsets = torch.arange(rules.shape[1], device=preds.device) * per_rule
    # In-place adds on int32 (when the bins fit) halve the memory traffic of this, the costly step;
    # chunks of pixels keep the K-fold index in cache (a sweep's is gigabytes at full size).
    dtype = torch.int32 if len(offsets) * per_rule < 2**31 else torch.long
    rules, rows = rules.flatten(2), (rows * n).flatten(1).unsqueeze(1).to(dtype)
    step = max(1, CONFUSION_CHUNK // (rules.shape[0] * rules.shape[1]))
    counts = torch.zeros(len(offsets) * per_rule, dtype=torch.long, device=preds.device)
    for s in range(0, rules.shape[2], step):
        index = rules[:, :, s : s + step].to(dtype, copy=True)
        index += rows[:, :, s : s + step]
        index += offsets.view(-1, 1).to(dtype)
        counts += torch.bincount(index.flatten(), minlength=len(counts))
    counts = counts.view(-1, r1, n + 1, n)[:, :, :n]
    cm = torch.cat([counts.sum(1, keepdim=True), counts[:, 1:]], dim=1)
    return cm if preds.ndim == 4 else cm[0]


def _tp_fp_fn(cm: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    if cm.ndim < 2 or cm.shape[-1] != cm.shape[-2]:
        raise ValueError(f"expected a (..., N, N) confusion matrix, got {_desc(cm)}")
    cm = cm.double()
    tp = cm.diagonal(dim1=-2, dim2=-1)
    return tp, cm.sum(-2) - tp, cm.sum(-1) - tp


def precision_recall(cm: Tensor) -> tuple[Tensor, Tensor]:
    """Per-class precision TP/(TP+FP) and recall TP/(TP+FN); 0/0 is NaN.

    Args:
        cm: (..., N, N) counts, rows = target, columns = prediction.

    Returns:
        Two float64 (..., N) tensors.

    >>> precision, recall = precision_recall(torch.tensor([[2, 0, 0], [1, 1, 0], [0, 0, 0]]))
    >>> precision.tolist(), recall.tolist()
    ([0.6666666666666666, 1.0, nan], [1.0, 0.5, nan])
    """
    tp, fp, fn = _tp_fp_fn(cm)
    return tp / (tp + fp), tp / (tp + fn)


def iou_from_confusion(cm: Tensor) -> Tensor:
    """Per-class IoU TP/(TP+FP+FN) of (..., N, N) counts → float64 (..., N); NaN where 0/0.

    >>> iou_from_confusion(torch.tensor([[2, 0, 0], [1, 1, 0], [0, 0, 0]]))
    tensor([0.6667, 0.5000,    nan], dtype=torch.float64)
    """
    tp, fp, fn = _tp_fp_fn(cm)
    return tp / (tp + fp + fn)


class Segments(NamedTuple):
    """The 8-connected components of one (H, W) mask."""

    labels: np.ndarray  # (H, W) component id per pixel, 0 = background
    count: int
    owner: np.ndarray  # (count + 1,) RoI id holding most pixels of each component (0 if no roi)


def label_segments(mask: np.ndarray, roi: np.ndarray | None, num_rois: int) -> Segments:
    """Label the 8-connected components of a (H, W) bool mask and find each one's RoI."""
    labels, count = ndimage.label(mask, structure=_EIGHT_CONNECTED)
    if roi is None:
        return Segments(labels, count, np.zeros(count + 1, dtype=np.int64))
    r1 = num_rois + 1
    votes = np.bincount(labels[mask] * r1 + roi[mask], minlength=(count + 1) * r1)
    # argmax takes the first maximum, so ties go to the lowest RoI id (SPEC §4).
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
    num_rois: int = 4,
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
            f"got {_desc(pred)} and {_desc(target)}"
        )
    if roi is not None and (not isinstance(roi, Tensor) or roi.shape != pred.shape):
        raise ValueError(
            f"expected roi None or an integer {tuple(pred.shape)} tensor, got {_desc(roi)}"
        )
    check_batch(pred[None], target[None], roi, num_rois)
    if cls < 0 or cls == ignore_index:
        raise ValueError(f"expected cls >= 0 and != ignore_index {ignore_index}, got {cls}")
    p, t = pred.cpu().numpy(), target.cpu().numpy()
    r = None if roi is None else roi.cpu().numpy()
    gt_mask = t == cls
    errors = mask_segment_errors((p == cls) & (t != ignore_index), gt_mask, r, num_rois)
    fp, fn, n_pred, n_gt = (int(v) for v in errors.counts[:, 0])
    out: dict[str, Any] = {"fp": fp, "fn": fn, "n_pred": n_pred, "n_gt": n_gt}
    out["fp_mask"] = torch.from_numpy(errors.fp_mask).to(pred.device)
    out["fn_mask"] = torch.from_numpy(errors.fn_mask).to(pred.device)
    if roi is not None:
        for i, key in enumerate(("fp_roi", "fn_roi", "n_pred_roi", "n_gt_roi")):
            out[key] = torch.from_numpy(errors.counts[i]).to(pred.device)
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
    """The core of SPEC §4's segment errors, shared by :func:`segment_errors` and
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
