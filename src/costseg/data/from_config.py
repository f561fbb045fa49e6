"""Datasets from a checkpoint's data configuration, without Lightning (fast start-up).

A costseg checkpoint stores how its data was built: the datamodule's class path and init args.
Evaluation needs only the un-augmented splits, so it builds them here directly.

>>> config = {"class_path": "costseg.data.datamodule.StreetScenesDataModule",
...           "init_args": {"size": [64, 128], "val_length": 2}}
>>> len(build_dataset(config, "val")), image_stems(build_dataset(config, "val"), [1])
(2, ['val_000001'])
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

from torch.utils.data import Dataset

SPLITS = ("train", "val", "test")


def cityscapes_config(root: str | Path) -> dict[str, Any]:
    """The data configuration of a Cityscapes tree at ``root`` (for networks costseg did not
    train)."""
    return {
        "class_path": "costseg.data.datamodule.CityscapesDataModule",
        "init_args": {"root": str(root)},
    }


def build_dataset(config: dict[str, Any], split: str, root: str | Path | None = None) -> Dataset:
    """The un-augmented ``split`` of the dataset described by ``config``.

    Args:
        config: ``{"class_path": ..., "init_args": {...}}`` as stored in a costseg checkpoint.
        split: "train", "val" or "test".
        root: a Cityscapes root that replaces the configured one (or the toy scenes).

    Raises:
        ValueError: an unknown split or dataset.
        FileNotFoundError: a missing Cityscapes tree.
    """
    if split not in SPLITS:
        raise ValueError(f"split must be one of {', '.join(SPLITS)}; got {split!r}")
    kind = config.get("class_path", "").rpartition(".")[2]
    args = dict(config.get("init_args", {}))
    if root is not None:
        kind, args = "CityscapesDataModule", {"root": str(root)}
    if kind == "StreetScenesDataModule":
        from costseg.data.toy import StreetScenes

        length = args.get(f"{split}_length", {"train": 2000, "val": 100, "test": 100}[split])
        return StreetScenes(split, length, tuple(args.get("size", (256, 512))), args.get("seed", 0))
    if kind == "CityscapesDataModule":
        from costseg.data.cityscapes import CityscapesSegmentation  # torchvision: only here

        folder = args.get("test_split", "val") if split == "test" else split
        return CityscapesSegmentation(args.get("root", "data/cityscapes"), folder)
    raise ValueError(f"unknown dataset {config.get('class_path')!r} in the data configuration")


def eval_batch_size(config: dict[str, Any], root: str | Path | None = None) -> int:
    """Images per evaluation batch the configuration asks for (Cityscapes: 2 full images)."""
    args = config.get("init_args", {})
    if root is not None or "root" in args:
        return int(args.get("eval_batch_size", 2)) if root is None else 2
    return int(args.get("batch_size", 8))


def image_stems(dataset: Dataset, indices: Sequence[int]) -> list[str]:
    """``frankfurt_000000_000294`` style names (Cityscapes) or ``<split>_<index>`` (toy)."""
    names = getattr(dataset, "names", None)
    if names is not None:
        return [names[i] for i in indices]
    split = getattr(dataset, "split", "data")
    return [f"{split}_{i:06d}" for i in indices]
