"""SegmentErrors: segment-wise false positives / negatives per rule, class and RoI (SPEC §4)."""

from __future__ import annotations

import functools
from collections.abc import Callable, Sequence

import numpy as np
import torch
import torch.nn.functional as F
from scipy import ndimage
from torch import Tensor

from costseg.classes import IGNORE_INDEX
from costseg.metrics.base import SumMetric
from costseg.metrics.functional import (
    as_rules,
    check_batch,
    label_segments,
    mask_segment_errors,
)
from costseg.threads import threads

_COUNTS = ("fp", "fn", "n_pred", "n_gt")


def _distinct(packed: np.ndarray) -> tuple[list[int], np.ndarray]:
    """Distinct rows of a (K, bytes) array: index of each one's first copy, (K,) inverse."""
    # Exact bytes as dict keys: hashing K packed rows is far cheaper than sorting them.
    first: dict[bytes, int] = {}
    reps: list[int] = []
    inverse = np.empty(len(packed), dtype=np.int64)
    for k, row in enumerate(packed):
        inverse[k] = first.setdefault(row.tobytes(), len(reps))
        if inverse[k] == len(reps):
            reps.append(k)
    return reps, inverse


_BITS = (128, 64, 32, 16, 8, 4, 2, 1)  # np.packbits' order: first pixel in the high bit


def packed_masks(rules: Tensor, cls: int, valid: Tensor) -> np.ndarray:
    """(B, K, ⌈H·W / 8⌉) uint8 on the CPU: ``np.packbits`` of each rule's mask ``rules == cls``
    on valid pixels, for (B, K, H, W) ``rules`` and (B, H, W) ``valid``. Off the CPU the bits are
    packed where the rules are, so 8 times fewer bytes are copied (K masks per class and image)."""
    masks = (rules == cls).logical_and_(valid.unsqueeze(1)).flatten(2)
    if masks.device.type == "cpu":
        return np.packbits(masks.numpy(), axis=-1)
    return _pack_bits(masks).cpu().numpy()


def _pack_bits(masks: Tensor) -> Tensor:
    """``np.packbits(masks, axis=-1)`` of a (B, K, P) bool tensor, in torch operations."""
    pad = -masks.shape[-1] % 8
    if pad:
        masks = torch.cat([masks, masks.new_zeros(*masks.shape[:-1], pad)], -1)
    bits = torch.tensor(_BITS, dtype=torch.uint8, device=masks.device)
    eights = masks.view(*masks.shape[:-1], -1, 8).to(torch.uint8)
    return eights.mul_(bits).sum(-1, dtype=torch.uint8)


def _rule_errors(
    packed: np.ndarray, gt_mask: np.ndarray, roi: np.ndarray | None, num_rois: int, maps: bool
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, np.ndarray | None]:
    """Segment errors of one class in one image under K rules, computed once per distinct mask.

    Args:
        packed: (K, ⌈H·W / 8⌉) uint8, each rule's mask ``pred == cls`` on non-ignored pixels,
            packed (:func:`packed_masks`).
        gt_mask: (H, W) bool, ``target == cls``.
        roi: None or (H, W) RoI ids.
        num_rois: R.
        maps: whether to return the FP / FN masks.

    Returns:
        (K,) index of each rule's distinct mask; (U, 4, R+1) int64 counts in the order of
        ``_COUNTS`` and (U, H, W) FP and FN masks (or None) of the U distinct masks.
    """
    reps, inverse = _distinct(packed)
    shape, size = gt_mask.shape, gt_mask.size
    if not maps and shape[1] % 64 == 0 and (runs := _compiled_runs()):  # rows of whole words
        prepare, run_counts = runs
        prepared = prepare(gt_mask, roi, num_rois, label_segments(gt_mask, roi, num_rois))
        counts = threads().map(lambda m: run_counts(m, shape, prepared), packed[reps])
        return inverse, np.stack(list(counts)), None, None
    unpack = lambda rows: np.unpackbits(rows, axis=-1, count=size).view(bool)  # noqa: E731
    # No segment reaches outside the box around all foreground: cropping to it changes nothing.
    union = unpack(np.bitwise_or.reduce(packed[reps], axis=0)).reshape(shape)
    boxes = ndimage.find_objects((union | gt_mask).view(np.uint8))
    box = boxes[0] if boxes else (slice(0, 0), slice(0, 0))
    crop = lambda row: unpack(row).reshape(shape)[box]  # noqa: E731  (on the threads)
    counts, fp, fn = _distinct_errors(
        packed[reps], crop, gt_mask[box], None if roi is None else roi[box], num_rois, maps
    )
    if fp is None or fn is None:
        return inverse, counts, None, None
    fp_full, fn_full = np.zeros((2, len(reps), *gt_mask.shape), dtype=bool)
    fp_full[:, box[0], box[1]], fn_full[:, box[0], box[1]] = fp, fn
    return inverse, counts, fp_full, fn_full


def _distinct_errors(
    packed: np.ndarray,
    crop: Callable[[np.ndarray], np.ndarray],
    gt_mask: np.ndarray,
    roi: np.ndarray | None,
    num_rois: int,
    maps: bool,
) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
    """Counts (U, 4, R+1) and, if ``maps``, FP / FN masks (U, h, w) of U packed masks, each
    unpacked and cropped to (h, w) by ``crop``; see above."""
    gt = label_segments(gt_mask, roi, num_rois)  # does not depend on the rule
    # One unpacking and labelling per mask, on threads: numpy's unpacking, scipy's labelling and
    # the compiled counting run without the GIL for the most part.
    if not maps and (counting := _compiled_counts()):
        counts = threads().map(lambda m: counting(crop(m), gt_mask, roi, num_rois, gt), packed)
        return np.stack(list(counts)), None, None
    errors = list(
        threads().map(lambda m: mask_segment_errors(crop(m), gt_mask, roi, num_rois, gt), packed)
    )
    counts = np.stack([e.counts for e in errors])
    if not maps:
        return counts, None, None
    return counts, np.stack([e.fp_mask for e in errors]), np.stack([e.fn_mask for e in errors])


def _packed_at_once(rules: Tensor, classes: tuple[int, ...], valid: Tensor) -> np.ndarray | None:
    """:func:`costseg.metrics.mask_bits.packed_class_masks` for uint8 rules (a grid of mixtures'
    label maps) where numba imports, else None (``packed_masks`` class by class)."""
    if rules.dtype != torch.uint8:
        return None
    try:
        from costseg.metrics.mask_bits import packed_class_masks
    except ImportError:
        return None
    return packed_class_masks(rules, classes, valid)


@functools.cache
def _compiled_runs():
    """:mod:`costseg.metrics.segment_runs`' ``Prepared`` and ``run_counts`` where numba imports,
    else None."""
    try:
        from costseg.metrics.segment_runs import Prepared, run_counts
    except ImportError:
        return None
    return Prepared, run_counts


@functools.cache
def _compiled_counts():
    """:func:`costseg.metrics.segment_counts.mask_counts` where numba imports, else None."""
    try:
        from costseg.metrics.segment_counts import mask_counts
    except ImportError:
        return None
    return mask_counts


class SegmentErrors(SumMetric):
    """Counts of false-positive / false-negative 8-connected segments and their location maps.

    Per decision rule k, class c and RoI r (r = 0: whole image) the states sum the numbers of FP
    and FN segments and of predicted and ground-truth segments (definitions: SPEC §4 and
    :func:`~costseg.metrics.functional.segment_errors`), plus per location the number of images
    in which it lies in an FP (resp. FN) segment. All states are sums, so the metric is the same
    in one batch, many batches or across processes.

    Args:
        classes: the C class ids to evaluate.
        num_rules: K, the number of decision rules in each ``preds``.
        num_rois: R.
        ignore_index: target value that is ignored.
        heatmap_size: (h, w) canvas of the FP / FN maps: each image's masks are resampled to
            it, so images of any size accumulate into one map. None takes the label size of
            the first update (under DDP pass it explicitly, so every process agrees); (0, 0)
            turns the maps off (for sweeps over many rules).

    ``compute()`` returns int64 (K, C, R+1) "fp", "fn", "n_pred", "n_gt"; float64 "fp_rate" =
    fp / n_pred and "fn_rate" = fn / n_gt (NaN for 0/0); float64 (K, C, h, w) "fp_map" and
    "fn_map": the fraction of images in which each location lies in an FP (FN) segment.

    >>> m = SegmentErrors(classes=(1,), num_rois=0)
    >>> m.update(torch.tensor([[[1, 0, 0], [0, 0, 1]]]), torch.tensor([[[1, 1, 0], [0, 0, 0]]]))
    >>> out = m.compute()
    >>> out["fp"].tolist(), out["n_pred"].tolist(), out["fp_map"][0, 0].tolist()
    ([[[1]]], [[[2]]], [[0.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    """

    def __init__(
        self,
        classes: Sequence[int] = (11, 2),
        num_rules: int = 1,
        num_rois: int = 4,
        ignore_index: int = IGNORE_INDEX,
        heatmap_size: tuple[int, int] | None = None,
    ) -> None:
        super().__init__()
        classes = tuple(int(c) for c in classes)
        if not classes or len(set(classes)) != len(classes) or ignore_index in classes:
            raise ValueError(
                f"expected distinct class ids other than {ignore_index}, got {classes}"
            )
        if num_rules < 1 or num_rois < 0:
            raise ValueError(f"expected num_rules >= 1, num_rois >= 0, got {num_rules}, {num_rois}")
        if heatmap_size is not None:
            heatmap_size = tuple(heatmap_size)
            if not (heatmap_size == (0, 0) or (len(heatmap_size) == 2 and min(heatmap_size) > 0)):
                raise ValueError(
                    f"expected heatmap_size None, (0, 0) or (h, w) > 0, got {heatmap_size}"
                )
        self.classes, self.num_rules, self.num_rois = classes, num_rules, num_rois
        self.ignore_index, self.heatmap_size = ignore_index, heatmap_size
        for name in _COUNTS:
            default = torch.zeros(num_rules, len(classes), num_rois + 1, dtype=torch.long)
            self.add_state(name, default)
        # With heatmap_size None the (1, 1) zero default broadcasts against the first label size,
        # which keeps forward() and merge_state() (both add states) working.
        size = (1, 1) if heatmap_size is None else heatmap_size
        for name in ("fp_map", "fn_map"):
            default = torch.zeros(num_rules, len(classes), *size, dtype=torch.float64)
            self.add_state(name, default)
        self.add_state("n_images", torch.zeros((), dtype=torch.long))

    @property
    def _maps_on(self) -> bool:
        return self.heatmap_size != (0, 0)

    def update(self, preds: Tensor, target: Tensor, roi: Tensor | None = None) -> None:
        """Add a batch: preds (B, K, H, W) (or (B, H, W) when K = 1), target (B, H, W), roi
        None, (H, W) or (B, H, W)."""
        rules = as_rules(preds, self.num_rules)
        check_batch(rules, target, roi, self.num_rois)
        rois = None if roi is None else roi.expand_as(target).cpu().numpy()
        fp_map, fn_map = self._map_states(tuple(target.shape[-2:]))
        valid = target != self.ignore_index
        packed = _packed_at_once(rules, self.classes, valid)
        for ci, cls in enumerate(self.classes):
            pred_masks = packed_masks(rules, cls, valid) if packed is None else packed[ci]
            gt_masks = (target == cls).cpu().numpy()
            for b in range(len(target)):
                r = None if rois is None else rois[b]
                inverse, counts, fp, fn = _rule_errors(
                    pred_masks[b], gt_masks[b], r, self.num_rois, self._maps_on
                )
                inverse = torch.from_numpy(inverse).to(self.device)
                counts = torch.from_numpy(counts).to(self.device)[inverse]
                for i, name in enumerate(_COUNTS):
                    getattr(self, name)[:, ci] += counts[:, i]
                if fp is not None:
                    fp_map[:, ci] += self._resample(fp)[inverse]
                    fn_map[:, ci] += self._resample(fn)[inverse]
        self.n_images += len(target)

    def _map_states(self, label_size: tuple[int, int]) -> tuple[Tensor, Tensor]:
        """The map states; with ``heatmap_size`` None the first label size becomes the canvas."""
        if self.heatmap_size is None and self.fp_map.shape[-2:] == (1, 1) and self.n_images == 0:
            self.fp_map = self.fp_map.new_zeros(*self.fp_map.shape[:2], *label_size)
            self.fn_map = self.fn_map.new_zeros(*self.fn_map.shape[:2], *label_size)
        return self.fp_map, self.fn_map

    def _resample(self, masks: np.ndarray) -> Tensor:
        """(U, H, W) bool masks → (U, h, w) on the canvas: area fractions (smaller canvas) or
        bilinear values (larger), on the metric's device."""
        maps = torch.from_numpy(masks).to(self.device)
        size = tuple(self.fp_map.shape[-2:])
        if maps.shape[-2:] == size:
            return maps  # bool: adding it to the float64 state needs no large float copy
        if size[0] <= maps.shape[-2] and size[1] <= maps.shape[-1]:
            return F.adaptive_avg_pool2d(maps.unsqueeze(1).float(), size).squeeze(1)
        resized = F.interpolate(maps.unsqueeze(1).float(), size, mode="bilinear", antialias=True)
        return resized.squeeze(1)

    def _compute(self) -> dict[str, Tensor]:
        """Counts, rates and maps of everything seen so far (shapes in the class docstring)."""
        out = {name: getattr(self, name) for name in _COUNTS}
        out["fp_rate"] = self.fp.double() / self.n_pred
        out["fn_rate"] = self.fn.double() / self.n_gt
        out["fp_map"] = self.fp_map / self.n_images
        out["fn_map"] = self.fn_map / self.n_images
        return out
