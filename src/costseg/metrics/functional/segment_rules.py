"""Segment errors of K decision rules at once: the update of :class:`~costseg.metrics.SegmentErrors`
and of the per-image losses (docs/definitions.md §4, §7).

The definition is :func:`~costseg.metrics.functional.segments.mask_segment_errors`, one mask at a
time. Here the K rules' masks of a class are packed to bits and identical masks (most of a sweep's)
are counted once, by :func:`rule_errors`: with location maps by the definition, without them by
the compiled pass over the masks' runs (:mod:`costseg.metrics.segment_runs`, tested equal).

>>> rules = torch.tensor([[[[1, 0, 1]], [[1, 0, 1]], [[0, 0, 0]]]])     # (B=1, K=3, 1, 3)
>>> target = torch.tensor([[[1, 0, 0]]])
>>> ((ci, b, errors),) = batch_segment_errors(rules, target, None, (1,), 0, maps=False)
>>> errors.inverse.tolist(), errors.counts[:, :, 0].tolist()    # two distinct masks
([0, 0, 1], [[1, 0, 2, 1], [0, 1, 0, 1]])
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import NamedTuple

import numpy as np
import torch
from scipy import ndimage
from torch import Tensor

from costseg.classes import IGNORE_INDEX
from costseg.metrics.functional.segments import label_segments, mask_segment_errors
from costseg.workers import threads

_BITS = (128, 64, 32, 16, 8, 4, 2, 1)  # np.packbits' order: first pixel in the high bit


class RuleErrors(NamedTuple):
    """Segment errors of one class in one image under K rules, once per distinct mask (U)."""

    inverse: np.ndarray  # (K,) int64: the distinct mask of each rule
    counts: np.ndarray  # (U, 4, R+1) int64: fp, fn, n_pred, n_gt (names.SEGMENT_COUNTS)
    fp: np.ndarray | None  # (U, H, W) bool pixels of FP segments, or None without maps
    fn: np.ndarray | None  # (U, H, W) bool pixels of FN segments, or None without maps


def distinct_rows(packed: np.ndarray) -> tuple[list[int], np.ndarray]:
    """Distinct rows of a (K, bytes) array: index of each one's first copy, (K,) inverse.

    >>> distinct_rows(np.array([[1, 2], [3, 4], [1, 2]], np.uint8))[1].tolist()
    [0, 1, 0]
    """
    # Exact bytes as dict keys: hashing K packed rows is far cheaper than sorting them.
    first: dict[bytes, int] = {}
    reps: list[int] = []
    inverse = np.empty(len(packed), dtype=np.int64)
    for k, row in enumerate(packed):
        inverse[k] = first.setdefault(row.tobytes(), len(reps))
        if inverse[k] == len(reps):
            reps.append(k)
    return reps, inverse


def packed_masks(rules: Tensor, cls: int, valid: Tensor) -> np.ndarray:
    """(B, K, ⌈H·W / 8⌉) uint8 on the CPU: ``np.packbits`` of each rule's mask ``rules == cls``
    on valid pixels, for (B, K, H, W) ``rules`` and (B, H, W) ``valid``. Off the CPU the bits are
    packed where the rules are, so 8 times fewer bytes are copied (K masks per class and image)."""
    masks = (rules == cls).logical_and_(valid.unsqueeze(1)).flatten(2)
    if masks.device.type == "cpu":
        return np.packbits(masks.numpy(), axis=-1)
    return pack_bits(masks).cpu().numpy()


def pack_bits(masks: Tensor) -> Tensor:
    """``np.packbits(masks, axis=-1)`` of a (B, K, P) bool tensor, in torch operations.

    >>> pack_bits(torch.tensor([[[True] + [False] * 8]])).tolist()
    [[[128, 0]]]
    """
    pad = -masks.shape[-1] % 8
    if pad:
        masks = torch.cat([masks, masks.new_zeros(*masks.shape[:-1], pad)], -1)
    bits = torch.tensor(_BITS, dtype=torch.uint8, device=masks.device)
    eights = masks.view(*masks.shape[:-1], -1, 8).to(torch.uint8)
    return eights.mul_(bits).sum(-1, dtype=torch.uint8)


def class_masks(rules: Tensor, classes: tuple[int, ...], valid: Tensor) -> Iterator[np.ndarray]:
    """:func:`packed_masks` of each class in turn; uint8 CPU rules (a grid of mixtures' label
    maps) are packed for every class in one compiled pass (:mod:`costseg.metrics.mask_bits`)."""
    at_once = None
    if rules.dtype == torch.uint8:
        from costseg.metrics.mask_bits import packed_class_masks  # numba: imported on need

        at_once = packed_class_masks(rules, classes, valid)
    for ci, cls in enumerate(classes):
        yield packed_masks(rules, cls, valid) if at_once is None else at_once[ci]


def rule_errors(
    packed: np.ndarray, gt_mask: np.ndarray, roi: np.ndarray | None, num_rois: int, maps: bool
) -> RuleErrors:
    """Segment errors of one class in one image under K rules, computed once per distinct mask.

    Args:
        packed: (K, ⌈H·W / 8⌉) uint8, each rule's mask ``pred == cls`` on non-ignored pixels,
            packed (:func:`packed_masks`).
        gt_mask: (H, W) bool, ``target == cls``.
        roi: None or (H, W) RoI ids.
        num_rois: R.
        maps: whether to return the FP / FN masks.
    """
    reps, inverse = distinct_rows(packed)
    shape, size = gt_mask.shape, gt_mask.size
    if not maps:  # the counts alone: one compiled pass over each distinct mask's runs
        from costseg.metrics.segment_runs import Prepared, run_counts  # numba: imported on need

        prepared = Prepared(gt_mask, roi, num_rois, label_segments(gt_mask, roi, num_rois))
        counts = threads().map(lambda m: run_counts(m, shape, prepared), packed[reps])
        return RuleErrors(inverse, np.stack(list(counts)), None, None)
    # The definition, with the maps: one unpacking and labelling per distinct mask, on threads
    # (numpy's unpacking and scipy's labelling run without the GIL for the most part).
    unpack = lambda rows: np.unpackbits(rows, axis=-1, count=size).view(bool)  # noqa: E731
    # No segment reaches outside the box around all foreground: cropping to it changes nothing.
    union = unpack(np.bitwise_or.reduce(packed[reps], axis=0)).reshape(shape)
    boxes = ndimage.find_objects((union | gt_mask).view(np.uint8))
    box = boxes[0] if boxes else (slice(0, 0), slice(0, 0))
    gt_box, roi_box = gt_mask[box], None if roi is None else roi[box]
    gt = label_segments(gt_box, roi_box, num_rois)  # does not depend on the rule
    errors = list(
        threads().map(
            lambda m: mask_segment_errors(
                unpack(m).reshape(shape)[box], gt_box, roi_box, num_rois, gt
            ),
            packed[reps],
        )
    )
    fp, fn = np.zeros((2, len(reps), *shape), dtype=bool)
    fp[:, box[0], box[1]] = np.stack([e.fp_mask for e in errors])
    fn[:, box[0], box[1]] = np.stack([e.fn_mask for e in errors])
    return RuleErrors(inverse, np.stack([e.counts for e in errors]), fp, fn)


def batch_segment_errors(
    rules: Tensor,
    target: Tensor,
    roi: Tensor | None,
    classes: tuple[int, ...],
    num_rois: int,
    maps: bool,
    ignore_index: int = IGNORE_INDEX,
) -> Iterator[tuple[int, int, RuleErrors]]:
    """``(class position, image, errors)`` of every class and image of a batch under K rules.

    Args:
        rules: (B, K, H, W) integer class ids (any device).
        target: (B, H, W) class ids or ``ignore_index``.
        roi: None, (H, W) or (B, H, W) RoI ids in 0..num_rois.
        classes: the class ids.
        num_rois: R.
        maps: whether the errors carry the FP / FN masks.
        ignore_index: target value that is ignored.
    """
    rois = None if roi is None else roi.expand_as(target).cpu().numpy()
    valid = target != ignore_index
    for ci, pred_masks in enumerate(class_masks(rules, classes, valid)):
        gt_masks = (target == classes[ci]).cpu().numpy()
        for b in range(len(target)):
            r = None if rois is None else rois[b]
            yield ci, b, rule_errors(pred_masks[b], gt_masks[b], r, num_rois, maps)
