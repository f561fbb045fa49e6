"""Instances missed entirely, per rule, class and RoI (``docs/definitions.md §9``).

Connected components merge touching objects (five pedestrians in a group are one segment), so
FN segments undercount the people a rule misses; instances count them one by one.

An instance is the set of pixels sharing an id ``label_id · 1000 + k`` (>= 1000) of a Cityscapes
``gtFine_instanceIds`` map, without its ignored pixels (label 255); ids below 1000 (stuff, crowd
regions) hold no instance. An instance of class c is **missed** by a rule when none of its
pixels is predicted c nor deferred (labelled ``DEFERRED``, §14: a deferred pedestrian is seen
as uncertain, not missed). It belongs to the RoI holding most of its pixels (ties: lowest id),
and its area (its pixels) is small below 32², medium below 96², else large, at 1024 × 2048
labels; for other sizes the limits scale with the label area. Every state is a sum, so batches and
processes merge exactly.

>>> ids = torch.tensor([[[24000, 24000, 0, 24001]]])            # two persons (train id 11)
>>> target = torch.tensor([[[11, 11, 0, 11]]])
>>> preds = torch.tensor([[[11, 0, 0, 0]]])                     # the second one is missed
>>> out = instance_misses(preds, target, ids, classes=(11,), num_rois=0)
>>> out.gt.sum().item(), out.missed.sum().item()
(2, 1)
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

import torch
import torch.nn.functional as F
from torch import Tensor

from costseg.classes import (
    IGNORE_INDEX,
    INSTANCE_OFFSET,
    LABEL_ID_TO_TRAIN_ID,
)
from costseg.decision.label_maps import DEFERRED
from costseg.metrics.functional.inputs import check_batch

AREA_NAMES = ("small", "medium", "large")
AREA_LIMITS = (32**2, 96**2)
"""Upper limits (pixels) of the small and medium instances at :data:`REFERENCE_SIZE`."""
REFERENCE_SIZE = (1024, 2048)
_TO_TRAIN = torch.from_numpy(LABEL_ID_TO_TRAIN_ID.astype("int64"))


class InstanceCounts(NamedTuple):
    """Per-image instance counts; the last axis is the RoI (index 0: whole image)."""

    gt: Tensor  # (B, C, A, R+1) int64 ground-truth instances by class, area bin and RoI
    missed: Tensor  # (B, K, C, A, R+1) int64 missed instances
    missed_mask: Tensor | None  # (B, K, C, H, W) bool pixels of missed instances, if asked


def area_limits(size: tuple[int, int]) -> tuple[float, float]:
    """The small / medium area limits for labels of (H, W) ``size``.

    >>> area_limits((1024, 2048)), area_limits((128, 256))
    ((1024.0, 9216.0), (16.0, 144.0))
    """
    scale = size[0] * size[1] / (REFERENCE_SIZE[0] * REFERENCE_SIZE[1])
    return AREA_LIMITS[0] * scale, AREA_LIMITS[1] * scale


def instance_misses(
    preds: Tensor,
    target: Tensor,
    instances: Tensor,
    classes: Sequence[int] = (11,),
    roi: Tensor | None = None,
    num_rois: int = 4,
    ignore_index: int = IGNORE_INDEX,
    masks: bool = False,
) -> InstanceCounts:
    """Ground-truth and missed instances of each image under K rules (definitions above).

    Args:
        preds: (B, H, W) or (B, K, H, W) integer class ids, or ``DEFERRED``.
        target: (B, H, W) train ids, ``ignore_index`` for ignored pixels.
        instances: (B, H, W) integer instance ids in Cityscapes' encoding.
        classes: the C instance classes (train ids) counted.
        roi: None, (H, W) or (B, H, W) RoI ids in 0..num_rois.
        num_rois: R.
        ignore_index: target value that is ignored.
        masks: also return the pixels of missed instances.

    Returns:
        :class:`InstanceCounts` on preds' device (A = 3 area bins of :data:`AREA_NAMES`).

    >>> ids = torch.tensor([[[26000, 26000], [26001, 26]]])     # two cars and a crowd pixel
    >>> out = instance_misses(torch.zeros(1, 2, 2, dtype=torch.long), torch.full((1, 2, 2), 13),
    ...                       ids, classes=(13,), num_rois=0, masks=True)
    >>> out.missed[0, 0, 0].tolist(), out.missed_mask[0, 0, 0].tolist()   # large: 2 px of 4
    ([[0], [0], [2]], [[True, True], [True, False]])
    """
    rules = preds.unsqueeze(1) if isinstance(preds, Tensor) and preds.ndim == 3 else preds
    check_batch(rules, target, roi, num_rois)
    if not isinstance(instances, Tensor) or instances.shape != target.shape:
        raise ValueError(f"expected instances of shape {tuple(target.shape)}, got {instances!r}")
    device = target.device
    wanted = torch.tensor([int(c) for c in classes], dtype=torch.long, device=device)
    position = torch.full((256,), -1, dtype=torch.long, device=device)
    position[wanted] = torch.arange(len(wanted), device=device)
    rois = None if roi is None else roi.expand_as(target)
    gt, missed, mask = [], [], []
    for b in range(len(target)):
        r = None if rois is None else rois[b]
        one = _one_image(rules[b], target[b], instances[b], r, position, wanted, num_rois,
                         ignore_index, masks)  # fmt: skip
        gt.append(one[0]), missed.append(one[1]), mask.append(one[2])
    return InstanceCounts(
        torch.stack(gt), torch.stack(missed), torch.stack(mask) if masks else None
    )


def _one_image(
    rules: Tensor,
    target: Tensor,
    ids: Tensor,
    roi: Tensor | None,
    position: Tensor,
    classes: Tensor,
    num_rois: int,
    ignore_index: int,
    masks: bool,
) -> tuple[Tensor, Tensor, Tensor | None]:
    """(C, A, R+1) instances, (K, C, A, R+1) missed and maybe (K, C, H, W) masks of one image."""
    k, (h, w), c, r1 = rules.shape[0], target.shape, len(classes), num_rois + 1
    flat = ids.flatten().long()
    label_id = torch.div(flat, INSTANCE_OFFSET, rounding_mode="floor").clamp(0, 255)
    pos = position[_TO_TRAIN.to(flat.device)[label_id]]
    counted = (flat >= INSTANCE_OFFSET) & (target.flatten() != ignore_index) & (pos >= 0)
    pix = counted.nonzero().squeeze(1)
    unique, member = torch.unique(flat[pix], return_inverse=True)  # sorted: deterministic
    m = len(unique)
    cls_pos = position[
        _TO_TRAIN.to(flat.device)[torch.div(unique, INSTANCE_OFFSET, rounding_mode="floor")]
    ]
    area = torch.bincount(member, minlength=m)
    owner = torch.zeros(m, dtype=torch.long, device=flat.device)
    if roi is not None:
        votes = torch.bincount(member * r1 + roi.flatten()[pix].long(), minlength=m * r1)
        owner = votes.view(m, r1).argmax(1)  # the first maximum: ties to the lowest RoI id
    small, medium = area_limits((h, w))
    size_bin = (area >= small).long() + (area >= medium).long()
    key = (cls_pos * len(AREA_NAMES) + size_bin) * r1 + owner  # (M,)
    cells = c * len(AREA_NAMES) * r1
    gt = _with_totals(torch.bincount(key, minlength=cells).view(c, len(AREA_NAMES), r1))
    labels = rules.flatten(1)[:, pix]  # (K, P)
    hits = (labels == classes[cls_pos][member]) | (labels == DEFERRED)
    hit = torch.zeros(k, m, dtype=torch.long, device=flat.device)
    hit.index_add_(1, member, hits.long())
    missed = hit == 0  # (K, M)
    rule, which = missed.nonzero(as_tuple=True)
    counts = torch.bincount(rule * cells + key[which], minlength=k * cells)
    missed_counts = _with_totals(counts.view(k, c, len(AREA_NAMES), r1))
    if not masks:
        return gt, missed_counts, None
    mask = torch.zeros(k, c, h * w, dtype=torch.bool, device=flat.device)
    mask[:, cls_pos[member], pix] = missed[:, member]
    return gt, missed_counts, mask.view(k, c, h, w)


def _with_totals(counts: Tensor) -> Tensor:
    """Counts by owning RoI (last axis) with index 0 replaced by the whole image's total."""
    counts = counts.clone()
    counts[..., 0] = counts.sum(-1)
    return counts


def resample_masks(masks: Tensor, size: tuple[int, int]) -> Tensor:
    """(..., H, W) bool masks on an (h, w) canvas: area fractions (smaller canvas) or bilinear
    values (larger); float32 (..., h, w).

    >>> resample_masks(torch.tensor([[True, False], [True, True]]), (1, 1)).tolist()
    [[0.75]]
    """
    lead, (h, w) = masks.shape[:-2], masks.shape[-2:]
    x = masks.reshape(-1, 1, h, w).float()
    if (h, w) == tuple(size):
        pass
    elif size[0] <= h and size[1] <= w:
        x = F.adaptive_avg_pool2d(x, size)
    else:
        x = F.interpolate(x, size, mode="bilinear", antialias=True)
    return x.view(*lead, *size)
