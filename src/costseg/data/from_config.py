"""The data settings, declared once: each datamodule's arguments with their defaults (training
takes them as its signature's defaults) and the un-augmented datasets they describe (evaluation
builds these without Lightning, for a fast start-up, from a checkpoint's data configuration: the
datamodule's class path and init args).

>>> config = {"class_path": "costseg.data.datamodule.StreetScenesDataModule",
...           "init_args": {"size": [64, 128], "val_length": 2}}
>>> len(build_dataset(config, "val")), image_stems(build_dataset(config, "val"), [1])
(2, ['val_000001'])
>>> data_settings(config).eval_batch_size, data_settings(config).num_workers
(8, 2)
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from torch.utils.data import Dataset

SPLITS = ("train", "val", "test")


@dataclass(frozen=True)
class StreetScenesSettings:
    """The arguments of :class:`~costseg.data.datamodule.StreetScenesDataModule` (see there)."""

    batch_size: int = 8
    num_workers: int = 2
    size: tuple[int, int] = (256, 512)
    train_length: int = 2000
    val_length: int = 100
    test_length: int = 100
    seed: int = 0
    prior_images: int | None = None

    @property
    def eval_batch_size(self) -> int:
        """Images per validation / test batch: the training batch size."""
        return self.batch_size

    def dataset(self, split: str, anomalies: bool = False) -> Dataset:
        """The un-augmented scenes of ``split`` (with unknown objects: docs/definitions.md §17)."""
        from costseg.data.toy import StreetScenes

        length = {"train": self.train_length, "val": self.val_length, "test": self.test_length}
        size = (int(self.size[0]), int(self.size[1]))
        return StreetScenes(split, length[split], size, self.seed, anomalies)


@dataclass(frozen=True)
class CityscapesSettings:
    """The arguments of :class:`~costseg.data.datamodule.CityscapesDataModule` (see there)."""

    root: str = "data/cityscapes"
    batch_size: int = 8
    num_workers: int = 4
    crop_size: int | tuple[int, int] = 768
    scale_range: tuple[float, float] = (0.5, 2.0)
    prior_images: int | None = None
    eval_batch_size: int = 2
    test_split: str = "val"

    def dataset(self, split: str, transform=None) -> Dataset:
        """The images of ``split`` (``test``: of ``test_split``), un-augmented without
        ``transform``."""
        from costseg.data.cityscapes import CityscapesSegmentation  # torchvision: only here

        folder = self.test_split if split == "test" else split
        return CityscapesSegmentation(self.root, folder, transform)


SETTINGS = {
    "StreetScenesDataModule": StreetScenesSettings,
    "CityscapesDataModule": CityscapesSettings,
}


def data_settings(
    config: dict[str, Any], root: str | Path | None = None
) -> StreetScenesSettings | CityscapesSettings:
    """The settings a data configuration describes, defaults filled in.

    Args:
        config: ``{"class_path": ..., "init_args": {...}}`` as stored in a costseg checkpoint.
        root: a Cityscapes root that replaces the configured dataset.

    Raises:
        ValueError: an unknown dataset or argument.
    """
    if root is not None:
        return CityscapesSettings(root=str(root))
    kind = SETTINGS.get(config.get("class_path", "").rpartition(".")[2])
    if kind is None:
        raise ValueError(f"unknown dataset {config.get('class_path')!r} in the data configuration")
    try:
        return kind(**config.get("init_args", {}))
    except TypeError as err:  # an argument the datamodule does not take
        raise ValueError(f"data configuration of {kind.__name__}: {err}") from None


def evaluated_data(config: dict[str, Any] | None, root: str | Path | None) -> dict[str, Any]:
    """The data configuration an evaluation reads: ``config``, or Cityscapes at ``root``
    (absolute) when a root replaces it.

    >>> evaluated_data(None, "/data/cs")["init_args"]
    {'root': '/data/cs'}
    """
    if root is None:
        if config is None:
            raise ValueError("no dataset named: neither a data configuration nor a root")
        return config
    cityscapes = "costseg.data.datamodule.CityscapesDataModule"
    return {"class_path": cityscapes, "init_args": {"root": str(Path(root).resolve())}}


def same_data(counted_on: dict[str, Any] | None, evaluated: dict[str, Any]) -> bool:
    """Whether priors counted on the data ``counted_on`` describes belong to ``evaluated``: the
    same procedural world, or Cityscapes at the same root (docs/definitions.md §3).

    >>> toy = {"class_path": "costseg.data.datamodule.StreetScenesDataModule", "init_args": {}}
    >>> same_data(toy, toy), same_data(toy, evaluated_data(None, "/data/cs"))
    (True, False)
    """
    if counted_on is None:
        return False
    before, now = data_settings(counted_on), data_settings(evaluated)
    if isinstance(now, CityscapesSettings):
        return isinstance(before, CityscapesSettings) and (
            Path(before.root).resolve() == Path(now.root).resolve()
        )
    return before == now


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
    return data_settings(config, root).dataset(split)


def image_stems(dataset: Dataset, indices: Sequence[int]) -> list[str]:
    """``frankfurt_000000_000294`` style names (Cityscapes) or ``<split>_<index>`` (toy)."""
    names = getattr(dataset, "names", None)
    if names is not None:
        return [names[i] for i in indices]
    split = getattr(dataset, "split", "data")
    return [f"{split}_{i:06d}" for i in indices]
