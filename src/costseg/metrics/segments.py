"""SegmentErrors: segment-wise false positives / negatives per rule, class and RoI, and where
they lie (docs/definitions.md §4); the core is :mod:`costseg.metrics.functional.segment_rules`."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor
from torchmetrics import Metric

from costseg.classes import IGNORE_INDEX, NUM_ROIS
from costseg.metrics.functional.inputs import as_rules, check_batch
from costseg.metrics.functional.segment_rules import batch_segment_errors
from costseg.metrics.names import SEGMENT_COUNTS, SEGMENT_RATE_PARTS
from costseg.metrics.shapes import KeepShapes


class SegmentErrors(KeepShapes, Metric):
    """Counts of false-positive / false-negative 8-connected segments and their location maps.

    Per decision rule k, class c and RoI r (r = 0: whole image) the states sum the numbers of FP
    and FN segments and of predicted and ground-truth segments (definitions: docs/definitions.md
    §4 and :func:`~costseg.metrics.functional.segment_errors`), plus per location the number of
    images in which it lies in an FP (resp. FN) segment. All states are sums, so the metric is
    the same in one batch, many batches or across processes.

    Args:
        classes: the C class ids to evaluate.
        num_rules: K, the number of decision rules in each ``preds``.
        num_rois: R.
        ignore_index: target value that is ignored.
        heatmap_size: (h, w) canvas of the FP / FN maps: each image's masks are resampled to
            it, so images of any size accumulate into one map. None takes the label size of
            the first update (under DDP pass it explicitly, so every process agrees); (0, 0)
            turns the maps off (for sweeps over many rules).
        kwargs: torchmetrics' options of every ``Metric`` (e.g. ``sync_on_compute``).

    ``compute()`` returns int64 (K, C, R+1) "fp", "fn", "n_pred", "n_gt"; float64 "fp_rate" =
    fp / n_pred and "fn_rate" = fn / n_gt (NaN for 0/0); float64 (K, C, h, w) "fp_map" and
    "fn_map": the fraction of images in which each location lies in an FP (FN) segment.

    >>> m = SegmentErrors(classes=(1,), num_rois=0)
    >>> m.update(torch.tensor([[[1, 0, 0], [0, 0, 1]]]), torch.tensor([[[1, 1, 0], [0, 0, 0]]]))
    >>> out = m.compute()
    >>> out["fp"].tolist(), out["n_pred"].tolist(), out["fp_map"][0, 0].tolist()
    ([[[1]]], [[[2]]], [[0.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    """

    is_differentiable = False
    higher_is_better = False
    full_state_update = False

    def __init__(
        self,
        classes: Sequence[int] = (11, 2),
        num_rules: int = 1,
        num_rois: int = NUM_ROIS,
        ignore_index: int = IGNORE_INDEX,
        heatmap_size: tuple[int, int] | None = None,
        **kwargs: Any,
    ) -> None:
        super().__init__(**kwargs)
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
        for name in SEGMENT_COUNTS:
            default = torch.zeros(num_rules, len(classes), num_rois + 1, dtype=torch.long)
            self.add_state(name, default, dist_reduce_fx="sum")
        # With heatmap_size None the (1, 1) zero default broadcasts against the first label size,
        # which keeps forward() and merge_state() (both add states) working.
        size = (1, 1) if heatmap_size is None else heatmap_size
        for name in ("fp_map", "fn_map"):
            default = torch.zeros(num_rules, len(classes), *size, dtype=torch.float64)
            self.add_state(name, default, dist_reduce_fx="sum")
        self.add_state("n_images", torch.zeros((), dtype=torch.long), dist_reduce_fx="sum")

    def update(self, preds: Tensor, target: Tensor, roi: Tensor | None = None) -> None:
        """Add a batch: preds (B, K, H, W) (or (B, H, W) when K = 1), target (B, H, W), roi
        None, (H, W) or (B, H, W)."""
        rules = as_rules(preds, self.num_rules)
        check_batch(rules, target, roi, self.num_rois)
        fp_map, fn_map = self._map_states(tuple(target.shape[-2:]))
        maps = self.heatmap_size != (0, 0)
        batch = batch_segment_errors(
            rules, target, roi, self.classes, self.num_rois, maps, self.ignore_index
        )
        for ci, _, errors in batch:
            inverse = torch.from_numpy(errors.inverse).to(self.device)
            counts = torch.from_numpy(errors.counts).to(self.device)[inverse]
            for i, name in enumerate(SEGMENT_COUNTS):
                getattr(self, name)[:, ci] += counts[:, i]
            if errors.fp is not None and errors.fn is not None:
                fp_map[:, ci] += self._resample(errors.fp)[inverse]
                fn_map[:, ci] += self._resample(errors.fn)[inverse]
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

    def compute(self) -> dict[str, Tensor]:
        """Counts, rates and maps of everything seen so far (shapes in the class docstring)."""
        out = {name: getattr(self, name) for name in SEGMENT_COUNTS}
        for rate, (part, whole) in SEGMENT_RATE_PARTS.items():
            out[rate] = out[part].double() / out[whole]
        out["fp_map"] = self.fp_map / self.n_images
        out["fn_map"] = self.fn_map / self.n_images
        return out
