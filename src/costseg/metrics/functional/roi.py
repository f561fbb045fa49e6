"""Pixel-wise confusion counts per decision rule and RoI, and what they give (docs/definitions.md
§4): precision, recall, IoU and mIoU.

Label maps hold train ids; pixels whose target is ``ignore_index`` count nowhere. RoI maps hold
ids 0..num_rois (0 = the location lies in no RoI); in every result, RoI index 0 is the whole
image and index r >= 1 the RoI with id r. A rule that defers a pixel (§14) labels it
``deferred`` (255): asked to, the counts give deferred pixels a last column of their own.
:func:`roi_confusion` is the definition; :func:`rule_confusion` the same counts for K rules at
once, faster (the update of :class:`~costseg.metrics.RoIPrecisionRecall`); :func:`roi_metrics`
its result (:mod:`.deferral` the metrics of deferred pixels).

>>> preds = torch.tensor([[[0, 1], [1, 1]]])
>>> target = torch.tensor([[[0, 1], [0, 255]]])
>>> cm = roi_confusion(preds, target, num_classes=2, num_rois=0)
>>> cm[0].tolist()                                   # rows = target, columns = prediction
[[1, 1], [0, 1]]
>>> [p.tolist() for p in precision_recall(cm[0])]
[[1.0, 0.5], [0.5, 1.0]]
"""

from __future__ import annotations

import torch
from torch import Tensor

from costseg.classes import IGNORE_INDEX, NUM_CLASSES, NUM_ROIS
from costseg.metrics.functional.deferral import deferral_metrics
from costseg.metrics.functional.inputs import as_rules, check_batch, describe
from costseg.metrics.names import PIXEL_RATE_PARTS

CONFUSION_CHUNK = 1 << 20  # rule x pixel entries indexed at once in roi_confusion
COMPILED_MIN_RULES = 16  # from this many rules on (sweeps), the CPU counts in one compiled pass;
# fewer do not pay for importing numba (about 0.8 s of an evaluation's start)


def roi_confusion(
    preds: Tensor,
    target: Tensor,
    roi: Tensor | None = None,
    num_classes: int = NUM_CLASSES,
    num_rois: int = NUM_ROIS,
    ignore_index: int = IGNORE_INDEX,
    deferred: int | None = None,
) -> Tensor:
    """Confusion matrices of the whole image and of each RoI, for one or K decision rules.

    Args:
        preds: (B, H, W) or (B, K, H, W) integer class ids in [0, num_classes) (or
            ``deferred``).
        target: (B, H, W) integer class ids, or ``ignore_index``.
        roi: None, (H, W) or (B, H, W) RoI ids in 0..num_rois (0 = in no RoI).
        num_classes: N.
        num_rois: R.
        ignore_index: target value that counts nowhere.
        deferred: the label of a deferred pixel (``costseg.decision.label_maps.DEFERRED``), a
            value >= N counted in column N; None: every prediction is a class.

    Returns:
        int64 (R+1, N, C), or (K, R+1, N, C) for 4-D preds, on preds' device (C = N, or N + 1
        with ``deferred``): ``cm[..., r, t, p]`` = pixels with target t and prediction p in RoI
        r (r = 0: whole image).

    >>> roi = torch.tensor([[1, 0], [1, 1]])
    >>> cm = roi_confusion(torch.ones(1, 2, 2, dtype=torch.long), torch.eye(2).long()[None], roi,
    ...                    num_classes=2, num_rois=1)
    >>> cm.tolist()                                  # whole image, then RoI 1
    [[[0, 2], [0, 2]], [[0, 1], [0, 2]]]
    >>> roi_confusion(torch.tensor([[[0, 255]]]), torch.tensor([[[1, 1]]]), num_classes=2,
    ...               num_rois=0, deferred=255).tolist()         # the last column: deferred
    [[[0, 0, 0], [1, 0, 1]]]
    """
    check_batch(preds, target, roi, num_rois)
    has_deferred = check_labels(preds, num_classes, deferred)
    bad = ((target < 0) | (target >= num_classes)) & (target != ignore_index)
    if bad.any():
        raise ValueError(
            f"expected target in [0, {num_classes}) or {ignore_index}, got {target[bad][0].item()}"
        )
    n, r1 = num_classes, num_rois + 1
    cols = n + (deferred is not None)
    rules = preds if preds.ndim == 4 else preds.unsqueeze(1)
    # Ignored pixels land in an extra target row n, dropped below: no boolean indexing needed.
    rows = torch.where(target == ignore_index, n, target.long())
    if roi is not None:
        rows = rows + roi.long().expand_as(target) * (n + 1)
    per_rule = r1 * (n + 1) * cols
    offsets = torch.arange(rules.shape[1], device=preds.device) * per_rule
    # In-place adds on int32 (when the bins fit) halve the memory traffic of this, the costly step;
    # chunks of pixels keep the K-fold index in cache (a sweep's is gigabytes at full size).
    dtype = torch.int32 if len(offsets) * per_rule < 2**31 else torch.long
    rules, rows = rules.flatten(2), (rows * cols).flatten(1).unsqueeze(1).to(dtype)
    step = max(1, CONFUSION_CHUNK // (rules.shape[0] * rules.shape[1]))
    counts = torch.zeros(len(offsets) * per_rule, dtype=torch.long, device=preds.device)
    for s in range(0, rules.shape[2], step):
        index = rules[:, :, s : s + step].to(dtype, copy=True)
        if has_deferred:
            index.masked_fill_(index == deferred, n)
        index += rows[:, :, s : s + step]
        index += offsets.view(-1, 1).to(dtype)
        counts += torch.bincount(index.flatten(), minlength=len(counts))
    counts = counts.view(-1, r1, n + 1, cols)[:, :, :n]
    cm = torch.cat([counts.sum(1, keepdim=True), counts[:, 1:]], dim=1)
    return cm if preds.ndim == 4 else cm[0]


def check_labels(preds: Tensor, num_classes: int, deferred: int | None) -> bool:
    """Raise ValueError unless every label is a class in [0, num_classes) or ``deferred``;
    returns whether some label is ``deferred``.

    >>> check_labels(torch.tensor([0, 255]), 2, 255), check_labels(torch.tensor([1]), 2, 255)
    (True, False)
    """
    if deferred is not None and deferred < num_classes:
        raise ValueError(f"the deferred label {deferred} is a class of {num_classes}")
    lo, hi = (int(v) for v in torch.aminmax(preds)) if preds.numel() else (0, 0)
    if lo >= 0 and hi < num_classes:
        return False
    outside = (preds < 0) | (preds >= num_classes)
    if deferred is None or (outside & (preds != deferred)).any():
        allowed = "" if deferred is None else f" or {deferred}"
        raise ValueError(f"expected preds in [0, {num_classes}){allowed}, got values in {lo}..{hi}")
    return True


def rule_confusion(
    preds: Tensor,
    target: Tensor,
    roi: Tensor | None,
    num_classes: int,
    num_rules: int,
    num_rois: int,
    ignore_index: int = IGNORE_INDEX,
    deferred: int | None = None,
) -> Tensor:
    """``roi_confusion`` of K rules, (K, R+1, N, C) int64, counted the fastest way for the input.

    Many rules on the CPU (a sweep) count in one compiled pass
    (:mod:`costseg.metrics.confusion_counts`); otherwise the pixels on which all K rules agree
    (most of them, in a sweep) are counted once for every rule, and only the others K times.

    Args:
        preds: (B, K, H, W), or (B, H, W) when ``num_rules`` is 1.
        target, roi, num_classes, num_rois, ignore_index, deferred: as in
            :func:`roi_confusion`.
        num_rules: K.
    """
    rules = as_rules(preds, num_rules)
    args = (num_classes, num_rois, ignore_index, deferred)
    if num_rules >= COMPILED_MIN_RULES and rules.device.type == "cpu":
        from costseg.metrics.confusion_counts import count_confusion  # numba: imported on need

        return count_confusion(rules, target, roi, *args)
    if num_rules == 1:
        return roi_confusion(rules, target, roi, *args)
    agree = (rules == rules[:, :1]).all(1)  # (B, H, W)
    roi = None if roi is None else roi.expand_as(target)
    flat = lambda t: t.view(1, 1, -1)  # noqa: E731  (one image of all selected pixels)
    shared = roi_confusion(
        flat(rules[:, 0][agree]),
        flat(target[agree]),
        None if roi is None else flat(roi[agree]),
        *args,
    )
    other = ~agree
    rest = rules.transpose(0, 1)[:, other].view(1, num_rules, 1, -1)
    rest_roi = None if roi is None else flat(roi[other])
    return shared + roi_confusion(rest, flat(target[other]), rest_roi, *args)


def tp_fp_fn(cm: Tensor, deferred: Tensor | None = None) -> tuple[Tensor, Tensor, Tensor]:
    """Per-class float64 (..., N) true positives, false positives and false negatives of
    (..., N, N) counts (rows = target, columns = prediction); the (..., N) ``deferred`` pixels
    of each target class, if given, are false negatives too."""
    if cm.ndim < 2 or cm.shape[-1] != cm.shape[-2]:
        raise ValueError(f"expected a (..., N, N) confusion matrix, got {describe(cm)}")
    cm = cm.double()
    tp = cm.diagonal(dim1=-2, dim2=-1)
    fn = cm.sum(-1) - tp
    return tp, cm.sum(-2) - tp, fn if deferred is None else fn + deferred.double()


def precision_recall(cm: Tensor, deferred: Tensor | None = None) -> tuple[Tensor, Tensor]:
    """Per-class precision TP/(TP+FP) and recall TP/(TP+FN); 0/0 is NaN.

    Args:
        cm: (..., N, N) counts, rows = target, columns = prediction.
        deferred: (..., N) pixels of each target class that were deferred (§14): false
            negatives of their class, predicted as no class.

    Returns:
        Two float64 (..., N) tensors.

    >>> precision, recall = precision_recall(torch.tensor([[2, 0, 0], [1, 1, 0], [0, 0, 0]]))
    >>> precision.tolist(), recall.tolist()
    ([0.6666666666666666, 1.0, nan], [1.0, 0.5, nan])
    >>> precision_recall(torch.tensor([[2, 0], [1, 1]]), torch.tensor([2, 0]))[1].tolist()
    [0.5, 0.5]
    """
    rates = pixel_rates(cm, deferred)
    return rates["precision"], rates["recall"]


def pixel_rates(cm: Tensor, deferred: Tensor | None = None) -> dict[str, Tensor]:
    """Every rate of :data:`~costseg.metrics.names.PIXEL_RATE_PARTS` per class of (..., N, N)
    counts (and the (..., N) ``deferred`` pixels, false negatives): float64 (..., N), NaN for
    0/0.

    >>> pixel_rates(torch.tensor([[2, 0], [1, 1]]))["precision"].tolist()
    [0.6666666666666666, 1.0]
    """
    tp, fp, fn = tp_fp_fn(cm, deferred)
    rates = {name: parts(tp, fp, fn) for name, parts in PIXEL_RATE_PARTS.items()}
    return {name: numerator / denominator for name, (numerator, denominator) in rates.items()}


def iou_from_confusion(cm: Tensor, deferred: Tensor | None = None) -> Tensor:
    """Per-class IoU TP/(TP+FP+FN) of (..., N, N) counts → float64 (..., N); NaN where 0/0. A
    deferred pixel (``deferred``: (..., N) per target class) is a false negative of its class.

    >>> iou_from_confusion(torch.tensor([[2, 0, 0], [1, 1, 0], [0, 0, 0]]))
    tensor([0.6667, 0.5000,    nan], dtype=torch.float64)
    """
    tp, fp, fn = tp_fp_fn(cm, deferred)
    return tp / (tp + fp + fn)


def mean_iou(cm: Tensor, deferred: Tensor | None = None) -> Tensor:
    """mIoU of (..., N, N) counts → float64 (...): the mean IoU over the classes whose IoU is
    defined (NaN where none is); a deferred pixel (``deferred``: (..., N)) is a false negative
    of its class (:func:`iou_from_confusion`).

    >>> mean_iou(torch.tensor([[2, 0, 0], [1, 1, 0], [0, 0, 0]])).item()   # (2/3 + 1/2) / 2
    0.5833333333333333
    >>> mean_iou(torch.tensor([[2, 0], [1, 1]]), torch.tensor([1, 0])).item()  # (1/2 + 1/2) / 2
    0.5
    """
    return iou_from_confusion(cm, deferred).nanmean(-1)


def roi_metrics(confmat: Tensor, deferred: Tensor | None = None) -> dict[str, Tensor]:
    """Everything :class:`~costseg.metrics.RoIPrecisionRecall` reports from its (K, R+1, N, N)
    counts of the pixels that were not deferred and its (K, R+1, N) deferred pixels per target
    class (None: none): "confmat", "deferred"; each pixel rate ("precision", "recall", ...) (K,
    R+1, N); "iou" (K, N)
    and "miou" (K,) over the whole image (the mean over the classes whose IoU is defined); the
    metrics of deferral (:func:`~costseg.metrics.functional.deferral.deferral_metrics`).

    >>> out = roi_metrics(torch.tensor([[[[2, 0], [1, 1]]]]))
    >>> out["recall"].tolist(), out["miou"].tolist(), out["coverage"].tolist()
    ([[[1.0, 0.5]]], [0.5833333333333333], [[[1.0, 1.0]]])
    """
    if deferred is None:
        deferred = confmat.new_zeros(confmat.shape[:-1])
    return {
        "confmat": confmat,
        "deferred": deferred,
        **pixel_rates(confmat, deferred),
        "iou": iou_from_confusion(confmat[:, 0], deferred[:, 0]),
        "miou": mean_iou(confmat[:, 0], deferred[:, 0]),
        **deferral_metrics(confmat, deferred),
    }
