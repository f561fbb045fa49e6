"""Statistics of the procedural street scenes: class frequencies, the RoI map, persons per RoI.

Run ``python scripts/toy_stats.py`` (defaults: ``toy.yaml``'s 128 x 256 scenes, priors
from the first 2000 training labels with the default smoothing, 100 validation scenes). Prints
the pixel frequency of each class over the training labels next to Cityscapes', the share of
each RoI in the RoI map and whether the sidewalk RoI (id 2) reaches both halves of the image,
and the ground-truth instances of person per owning RoI over the validation scenes
(docs/definitions.md §3, §9).
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from dataclasses import dataclass

import numpy as np
import torch

from costseg.classes import CLASS_NAMES, IGNORE_INDEX, NUM_CLASSES, ROI_NAMES, class_index
from costseg.cli import parse_options
from costseg.data.priors import pixel_priors, roi_map
from costseg.data.toy.dataset import StreetScenes
from costseg.metrics.functional.instances import instance_misses
from costseg.options import option
from costseg.values import whole_number

# Cityscapes' pixel frequencies (%) over the labelled pixels of the fine training annotations.
CITYSCAPES = {"road": 36.9, "building": 22.8, "vegetation": 15.9, "car": 7.0, "sidewalk": 6.1,
              "sky": 4.0, "person": 1.2}  # fmt: skip


@dataclass
class StatsOptions:
    """What ``toy_stats.py`` can be told (``--help``)."""

    size: list[int] = option(
        [128, 256], "the scenes' size", type=whole_number(1), nargs=2, metavar=("H", "W")
    )
    prior_images: int = option(2000, "training labels", type=whole_number(1))
    val: int = option(100, "validation scenes", type=whole_number(1))
    seed: int = option(0, "the scenes' seed", type=whole_number(0))


def class_frequencies(labels: Iterator[torch.Tensor]) -> np.ndarray:
    """(N,) percentage of the labelled pixels of ``labels`` that hold each class."""
    counts = np.zeros(NUM_CLASSES)
    for label in labels:
        counts += np.bincount(label[label != IGNORE_INDEX].numpy(), minlength=NUM_CLASSES)
    return 100 * counts / counts.sum()


def sidewalk_sides(roi: torch.Tensor) -> tuple[bool, bool]:
    """Whether RoI id 2 (sidewalk) occurs in the left and in the right half of an (H, W) map.

    >>> sidewalk_sides(torch.tensor([[2, 1, 1, 2]])), sidewalk_sides(torch.tensor([[1, 2]]))
    ((True, True), (False, True))
    """
    half = roi.shape[1] // 2
    return bool((roi[:, :half] == 2).any()), bool((roi[:, half:] == 2).any())


def persons_per_roi(scenes: StreetScenes, roi: torch.Tensor) -> list[int]:
    """Ground-truth person instances of ``scenes`` per owning RoI (index 0: all of them)."""
    person, total = class_index("person"), torch.zeros(len(ROI_NAMES), dtype=torch.long)
    for i in range(len(scenes)):
        _, label, ids = scenes.with_instances(i)
        out = instance_misses(
            label[None, None].clamp(max=18), label[None], ids[None], (person,), roi
        )
        total += out.gt[0, 0].sum(0)
    return total.tolist()


def main(args: Sequence[str] | None = None) -> None:
    args = parse_options(StatsOptions, args, "toy_stats.py", __doc__.splitlines()[0])
    size = tuple(args.size)
    train = StreetScenes("train", args.prior_images, size, args.seed)
    labels = [train[i][1] for i in range(len(train))]
    freq = class_frequencies(iter(labels))
    print(f"class frequencies over {len(labels)} training labels at {size[0]}x{size[1]} (%):")
    for c in np.argsort(-freq):
        ref = CITYSCAPES.get(CLASS_NAMES[c])
        print(f"  {CLASS_NAMES[c]:<14}{freq[c]:6.2f}" + (f"   Cityscapes {ref:.1f}" if ref else ""))
    roi = roi_map(pixel_priors(labels, progress=False))
    shares = torch.bincount(roi.flatten(), minlength=len(ROI_NAMES)).double() / roi.numel()
    parts = [f"{r} {ROI_NAMES[r]} {100 * shares[r]:.1f} %" for r in range(1, len(ROI_NAMES))]
    print("RoI map (default smoothing): " + ", ".join(parts))
    left, right = sidewalk_sides(roi)
    print(f"sidewalk RoI in the left half: {left}, in the right half: {right}")
    val = StreetScenes("val", args.val, size, args.seed)
    counts = persons_per_roi(val, roi)
    parts = [f"{r} {ROI_NAMES[r]} {n}" for r, n in enumerate(counts)]
    print(f"person instances over {args.val} validation scenes by owning RoI: " + ", ".join(parts))


if __name__ == "__main__":
    main()
