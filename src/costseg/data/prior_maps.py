"""Pixel-wise priors and the RoI map at every image size an evaluation meets.

Priors are stored at label resolution; images of other sizes get them resized bilinearly
(docs/definitions.md §3), once per size. FP/FN location heatmaps of all images go onto one fixed
canvas.

>>> maps = PriorMaps(torch.full((19, 4, 8), 1 / 19), device=torch.device("cpu"))
>>> [tuple(t.shape) for t in maps.at((2, 4))]
[(19, 2, 4), (2, 4)]
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from PIL import Image
from torch import Tensor
from torch.utils.data import Dataset

from costseg.classes import CLASS_NAMES
from costseg.data.priors import check_priors, geometric_roi_map, resize_priors, roi_map

MAX_CANVAS_WIDTH = 512


class PriorMaps:
    """Priors (N, H, W) and RoI map (H, W) per image size, resized on first use and kept.

    Args:
        priors: (N, H, W) priors at label resolution, finite and > 0 (checked: ValueError), or
            None (then ``at`` gives no priors).
        class_names: class per channel (must include the RoI classes).
        device: where the resized maps live.
        geometric: RoIs from :func:`~costseg.data.priors.geometric_roi_map` at each size instead
            of the priors' map (data without training labels, docs/definitions.md §3).
    """

    def __init__(
        self,
        priors: Tensor | None,
        class_names: Sequence[str] = CLASS_NAMES,
        device: torch.device | None = None,
        geometric: bool = False,
    ) -> None:
        if priors is not None:  # whatever their source: a file, a checkpoint, a tensor given
            check_priors(priors, class_names)
        self.priors = None if priors is None else priors.to(device or "cpu")
        self.class_names = class_names
        self.device = device
        self.geometric = geometric
        self._cache: dict[tuple[int, int], tuple[Tensor | None, Tensor | None]] = {}

    def at(self, size: tuple[int, int]) -> tuple[Tensor | None, Tensor | None]:
        """(priors (N, h, w) or None, roi (h, w) or None) at ``size``."""
        size = (int(size[0]), int(size[1]))
        if size not in self._cache:
            resized = None if self.priors is None else resize_priors(self.priors, size)
            self._cache[size] = (resized, self._roi(resized, size))
        return self._cache[size]

    def roi_map(self, size: tuple[int, int] | None = None) -> Tensor | None:
        """(H, W) RoI map (CPU) at the priors' own resolution, or at ``size`` (the geometric
        map's default: 256 x 512); None without priors and without the geometric map."""
        if size is None and self.priors is not None:
            size = tuple(self.priors.shape[-2:])
        roi = self._roi(self.priors, size or (256, 512))
        return None if roi is None else roi.cpu()

    def _roi(self, priors: Tensor | None, size: tuple[int, int]) -> Tensor | None:
        if self.geometric:
            return geometric_roi_map(size).to(self.device or "cpu")
        return None if priors is None else roi_map(priors, self.class_names)


def heatmap_canvas(dataset: Dataset) -> tuple[int, int]:
    """(h, w) of the FP/FN location maps: the first label's size, at most 512 wide.

    Every image's segments are resampled onto this one canvas, so datasets with mixed
    resolutions accumulate into the same maps (and processes agree on the shape).
    """
    files = getattr(dataset, "files", None)
    if files:
        with Image.open(files[0][1]) as label:
            h, w = label.height, label.width
    else:
        h, w = dataset[0][1].shape[-2:]
    scale = min(1.0, MAX_CANVAS_WIDTH / w)
    return max(1, round(h * scale)), max(1, round(w * scale))
