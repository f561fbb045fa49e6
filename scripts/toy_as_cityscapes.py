"""Write procedural street scenes in Cityscapes' folder layout and label-id encoding.

A stand-in tree for running ``--config cityscapes`` end to end (data loading at full resolution,
augmentation, bf16 training, validation) on a machine without Cityscapes:

    python scripts/toy_as_cityscapes.py /tmp/cityscapes --train 160 --val 16
    python train.py --config cityscapes --data.init_args.root /tmp/cityscapes

Images go to ``leftImg8bit/<split>/toy/toy_000000_<index>_leftImg8bit.png`` and labels, as
Cityscapes label ids (train id 255 becomes id 0, "unlabeled"), to
``gtFine/<split>/toy/toy_000000_<index>_gtFine_labelIds.png``, with instance ids in Cityscapes'
encoding (``label_id · 1000 + k``; below 1000 the plain label id) as 16-bit PNGs,
``..._gtFine_instanceIds.png``.
"""

from __future__ import annotations

from collections.abc import Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from functools import partial
from pathlib import Path

import numpy as np
from PIL import Image

from costseg import workers
from costseg.classes import TRAIN_ID_TO_LABEL_ID
from costseg.cli import parse_options
from costseg.data.cityscapes import IMAGE_SUFFIX, INSTANCE_SUFFIX, LABEL_SUFFIX
from costseg.data.toy import StreetScenes
from costseg.options import option
from costseg.values import positive_number, whole_number

_TO_LABEL_ID = np.zeros(256, dtype=np.uint8)  # everything else, incl. 255, is "unlabeled" (0)
_TO_LABEL_ID[: len(TRAIN_ID_TO_LABEL_ID)] = TRAIN_ID_TO_LABEL_ID


@dataclass
class TreeOptions:
    """What ``toy_as_cityscapes.py`` can be told (``--help``)."""

    root: Path | None = option(help="folder to create", type=Path, flag="ROOT")
    train: int = option(160, "training images", type=whole_number(0))
    val: int = option(16, "validation images", type=whole_number(0))
    size: list[int] = option(
        [1024, 2048], "the scenes' size", type=whole_number(1), nargs=2, metavar=("H", "W")
    )
    seed: int = option(0, "the scenes' seed", type=whole_number(0))
    workers: int | None = option(help="processes (default: all)", type=whole_number(1))
    image_scale: float = option(
        1.0,
        "images resized by this factor beside full-size labels (0.5: half-resolution)",
        type=positive_number,
    )


def write_item(scenes: StreetScenes, root: Path, index: int, image_scale: float = 1.0) -> None:
    """Write scene ``index`` of ``scenes`` as an image (resized by ``image_scale``), a label-id and
    an instance-id PNG."""
    image, train_ids, instance_ids = scenes.with_instances(index)
    name = f"toy_000000_{index:06d}"
    for folder, suffix, array in (
        ("leftImg8bit", IMAGE_SUFFIX, image.permute(1, 2, 0).numpy()),
        ("gtFine", LABEL_SUFFIX, _TO_LABEL_ID[train_ids.numpy()]),
        ("gtFine", INSTANCE_SUFFIX, instance_ids.numpy().astype(np.uint16)),
    ):
        path = root / folder / scenes.split / "toy" / f"{name}{suffix}"
        path.parent.mkdir(parents=True, exist_ok=True)
        picture = Image.fromarray(array)
        if folder == "leftImg8bit" and image_scale != 1:
            size = (round(picture.width * image_scale), round(picture.height * image_scale))
            picture = picture.resize(size, Image.Resampling.BILINEAR)
        picture.save(path, compress_level=1)


def main(args: Sequence[str] | None = None) -> None:
    opts = parse_options(TreeOptions, args, "toy_as_cityscapes.py", __doc__.splitlines()[0])
    with ProcessPoolExecutor(opts.workers, mp_context=workers.CONTEXT) as pool:
        for split, count in (("train", opts.train), ("val", opts.val)):
            scenes = StreetScenes(split, count, tuple(opts.size), opts.seed)
            write = partial(write_item, scenes, opts.root, image_scale=opts.image_scale)
            list(pool.map(write, range(count), chunksize=4))
    print(f"wrote {opts.train} train and {opts.val} val scenes of {opts.size} to {opts.root}")


if __name__ == "__main__":
    main()
