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
from costseg.data.priors import resize_priors, roi_map

MAX_CANVAS_WIDTH = 512


class PriorMaps:
    """Priors (N, H, W) and RoI map (H, W) per image size, resized on first use and kept.

    Args:
        priors: (N, H, W) priors at label resolution, or None (then ``at`` gives Nones).
        class_names: class per channel (must include the RoI classes).
        device: where the resized maps live.
    """

    def __init__(
        self,
        priors: Tensor | None,
        class_names: Sequence[str] = CLASS_NAMES,
        device: torch.device | None = None,
    ) -> None:
        self.priors = None if priors is None else priors.to(device or "cpu")
        self.class_names = class_names
        self._cache: dict[tuple[int, int], tuple[Tensor, Tensor]] = {}

    def at(self, size: tuple[int, int]) -> tuple[Tensor | None, Tensor | None]:
        """(priors (N, h, w), roi (h, w)) at ``size``; (None, None) without priors."""
        if self.priors is None:
            return None, None
        size = (int(size[0]), int(size[1]))
        if size not in self._cache:
            resized = resize_priors(self.priors, size)
            self._cache[size] = (resized, roi_map(resized, self.class_names))
        return self._cache[size]

    def roi_map(self) -> Tensor | None:
        """(H, W) RoI map at the priors' own resolution (CPU), or None."""
        if self.priors is None:
            return None
        return roi_map(self.priors, self.class_names).cpu()


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
