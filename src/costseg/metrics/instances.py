"""Instances missed entirely as a :class:`torchmetrics.Metric` (docs/definitions.md §9); the
functional core is :mod:`costseg.metrics.functional.instances`."""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor
from torchmetrics import Metric

from costseg.classes import IGNORE_INDEX, INSTANCE_CLASSES
from costseg.metrics.functional.inputs import as_rules
from costseg.metrics.functional.instances import AREA_NAMES, instance_misses, resample_masks
from costseg.metrics.shapes import KeepShapes


class InstanceMisses(KeepShapes, Metric):
    """Ground-truth and missed instances per rule, class, area and RoI, and where the missed
    ones lie (``docs/definitions.md §9``; the functional core is :func:`instance_misses`).

    Args:
        classes: the C instance classes (train ids of :data:`~costseg.classes.INSTANCE_CLASSES`).
        num_rules: K, the rules in each ``preds``.
        num_rois: R.
        ignore_index: target value that is ignored.
        heatmap_size: (h, w) canvas of the location map of missed instances (each image's
            masks are resampled to it); (0, 0) turns the map off (sweeps over many rules).

    ``compute()`` returns int64 (C,) "classes"; int64 (K, C, R+1) "gt_instances",
    "missed_instances" and "missed_small" / "missed_medium" / "missed_large", "gt_small" /
    "gt_medium" / "gt_large"; float64 (K, C, R+1) "instance_recall" = 1 − missed / instances (NaN
    without instances); float64 (K, C, h, w) "missed_map", the fraction of images in which each
    location lies in a missed instance; int64 "n_images". torchmetrics squeezes one-element
    results to 0-d; :meth:`shaped` gives them these shapes back.

    >>> m = InstanceMisses(classes=(11,), num_rois=0)
    >>> m.update(torch.tensor([[[11, 0, 0]]]), torch.tensor([[[11, 11, 11]]]),
    ...          torch.tensor([[[24000, 24001, 24001]]]))
    >>> out = m.compute()
    >>> out["gt_instances"].tolist(), out["missed_instances"].tolist(), out["instance_recall"]
    ([[[2]]], [[[1]]], tensor([[[0.5000]]], dtype=torch.float64))
    """

    full_state_update = False
    is_differentiable = False
    higher_is_better = None

    def __init__(
        self,
        classes: Sequence[int] = (11,),
        num_rules: int = 1,
        num_rois: int = 4,
        ignore_index: int = IGNORE_INDEX,
        heatmap_size: tuple[int, int] = (0, 0),
    ) -> None:
        super().__init__()
        classes = tuple(int(c) for c in classes)
        if (
            not classes
            or len(set(classes)) != len(classes)
            or not set(classes) <= set(INSTANCE_CLASSES)
        ):
            raise ValueError(
                f"expected distinct instance classes (train ids {INSTANCE_CLASSES}), got {classes}"
            )
        size = tuple(int(s) for s in heatmap_size)
        if num_rules < 1 or num_rois < 0 or len(size) != 2 or min(size) < 0:
            raise ValueError(f"bad num_rules {num_rules}, num_rois {num_rois} or size {size}")
        self.classes, self.num_rules, self.num_rois = classes, num_rules, num_rois
        self.ignore_index, self.heatmap_size = ignore_index, size
        c, a, r1 = len(classes), len(AREA_NAMES), num_rois + 1
        self.add_state("gt", torch.zeros(c, a, r1, dtype=torch.long), dist_reduce_fx="sum")
        zeros = torch.zeros(num_rules, c, a, r1, dtype=torch.long)
        self.add_state("missed", zeros, dist_reduce_fx="sum")
        zeros = torch.zeros(num_rules, c, *size, dtype=torch.float64)
        self.add_state("missed_map", zeros, dist_reduce_fx="sum")
        self.add_state("n_images", torch.zeros((), dtype=torch.long), dist_reduce_fx="sum")

    def update(
        self, preds: Tensor, target: Tensor, instances: Tensor, roi: Tensor | None = None
    ) -> None:
        """Add a batch: preds (B, K, H, W) (or (B, H, W) when K = 1), target and instances
        (B, H, W), roi None, (H, W) or (B, H, W)."""
        rules = as_rules(preds, self.num_rules)
        maps = min(self.heatmap_size) > 0
        out = instance_misses(
            rules, target, instances, self.classes, roi, self.num_rois, self.ignore_index, maps
        )
        self.gt += out.gt.sum(0)
        self.missed += out.missed.sum(0)
        if out.missed_mask is not None:
            self.missed_map += resample_masks(out.missed_mask, self.heatmap_size).sum(0)
        self.n_images += len(target)

    def compute(self) -> dict[str, Tensor]:
        """Counts, recall and map of everything seen so far (shapes in the class docstring)."""
        k = self.num_rules
        gt = self.gt.sum(1).expand(k, -1, -1)
        missed = self.missed.sum(2)
        out = {
            "classes": torch.tensor(self.classes, device=self.gt.device),
            "gt_instances": gt.clone(),
            "missed_instances": missed,
            "instance_recall": 1 - missed.double() / gt,
        }
        for a, name in enumerate(AREA_NAMES):
            out[f"gt_{name}"] = self.gt[:, a].expand(k, -1, -1).clone()
            out[f"missed_{name}"] = self.missed[:, :, a]
        out["missed_map"] = self.missed_map / self.n_images
        out["n_images"] = self.n_images
        return out
