"""LightningDataModules for the procedural street scenes and for Cityscapes.

Both give batches ``(images, labels)``: (B, 3, H, W) uint8 RGB and (B, H, W) int64 train ids
(255 = ignore); normalising the images is the model's job. Worker seeding is left to Lightning:
``seed_everything(workers=True)`` (the CLI calls it) makes the trainer add a worker init function,
so shuffling and augmentation are reproducible for a given seed and worker count.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from pathlib import Path
from typing import Any

import torch
from lightning.pytorch import LightningDataModule
from PIL import Image
from torch import Tensor
from torch.utils.data import DataLoader, Dataset, Subset
from torchvision import tv_tensors
from torchvision.transforms import v2

from costseg import workers
from costseg.classes import CLASS_NAMES, NUM_CLASSES
from costseg.data.cityscapes import CityscapesSegmentation, train_transform
from costseg.data.from_config import CityscapesSettings, StreetScenesSettings

Pair = tuple[Tensor, Tensor]
TOY, CITYSCAPES = StreetScenesSettings(), CityscapesSettings()  # the defaults, declared there


class _Augmented(Dataset[Pair]):
    """A (image, label) dataset with a joint ``torchvision.transforms.v2`` transform applied."""

    def __init__(self, dataset: Dataset[Pair], transform: v2.Transform) -> None:
        self.dataset, self.transform = dataset, transform

    def __len__(self) -> int:
        return len(self.dataset)  # type: ignore[arg-type]

    def __getitem__(self, index: int) -> Pair:
        image, label = self.dataset[index]
        image, label = self.transform(tv_tensors.Image(image), tv_tensors.Mask(label))
        return image.as_subclass(Tensor), label.as_subclass(Tensor)


class _Labels(Dataset[Tensor]):
    """The labels of a dataset, through its image-free ``read_label`` when it has one."""

    def __init__(self, dataset: Dataset[Pair]) -> None:
        self.dataset = dataset

    def __len__(self) -> int:
        return len(self.dataset)  # type: ignore[arg-type]

    def __getitem__(self, index: int) -> Tensor:
        if isinstance(self.dataset, CityscapesSegmentation):
            return self.dataset.read_label(index)
        return self.dataset[index][1]


class _SegmentationDataModule(LightningDataModule, ABC):
    """Dataloaders and prior labels shared by both datasets; subclasses build the datasets."""

    num_classes: int = NUM_CLASSES
    class_names: tuple[str, ...] = CLASS_NAMES

    def __init__(
        self, batch_size: int, num_workers: int, prior_images: int | None, eval_batch_size: int
    ) -> None:
        super().__init__()
        for name, value, low in (
            ("batch_size", batch_size, 1),
            ("eval_batch_size", eval_batch_size, 1),
            ("num_workers", num_workers, 0),
            ("prior_images", 1 if prior_images is None else prior_images, 1),
        ):
            if not isinstance(value, int) or value < low:
                raise ValueError(f"{name} must be an integer >= {low}; got {value!r}")
        self.batch_size, self.eval_batch_size = batch_size, eval_batch_size
        self.num_workers, self.prior_images = num_workers, prior_images
        self._datasets: dict[str, Dataset] = {}

    @abstractmethod
    def make_dataset(self, split: str, augment: bool) -> Dataset[Pair]:
        """The ``"train"``, ``"val"`` or ``"test"`` dataset; ``augment`` only for training."""

    def _dataset(self, split: str) -> Dataset[Pair]:
        if split not in self._datasets:
            self._datasets[split] = self.make_dataset(split, augment=split == "train")
        return self._datasets[split]

    def setup(self, stage: str) -> None:
        splits = {"fit": ("train", "val"), "validate": ("val",)}.get(stage, ("test",))
        for split in splits:
            self._dataset(split)

    def _loader(self, split: str) -> DataLoader[Pair]:
        train = split == "train"
        return DataLoader(
            self._dataset(split),
            batch_size=self.batch_size if train else self.eval_batch_size,
            shuffle=train,
            drop_last=train,
            persistent_workers=self.num_workers > 0,
            **workers.loader_options(self.num_workers),
            pin_memory=torch.cuda.is_available(),
        )

    def train_dataloader(self) -> DataLoader[Pair]:
        return self._loader("train")

    def val_dataloader(self) -> DataLoader[Pair]:
        return self._loader("val")

    def test_dataloader(self) -> DataLoader[Pair]:
        return self._loader("test")

    @abstractmethod
    def prior_key(self) -> dict[str, Any]:
        """What the labels of :meth:`prior_labels` depend on, JSON-like: the data, not how it
        is loaded (batch size, workers, crops); the key of the priors' cache."""

    def prior_labels(self) -> DataLoader[Tensor]:
        """Un-augmented (H, W) int64 training labels, the first ``prior_images`` (None = all).

        Returns:
            A DataLoader yielding one label at a time (it has ``len``, so progress bars know
            the total); labels are read in ``num_workers`` processes.
        """
        labels = _Labels(self.make_dataset("train", augment=False))
        count = len(labels) if self.prior_images is None else min(self.prior_images, len(labels))
        return DataLoader(
            Subset(labels, range(count)),
            batch_size=None,
            **workers.loader_options(self.num_workers),
        )


class StreetScenesDataModule(_SegmentationDataModule):
    """Procedural street scenes (:class:`costseg.data.toy.StreetScenes`); no download needed.

    Training items get random horizontal flips only: every index is already a different scene,
    so heavier augmentation would add little.

    Args:
        batch_size: Images per batch (training, validation and test).
        num_workers: Dataloader worker processes (0 = load in the main process).
        size: (H, W) of images and labels, each >= 64.
        train_length: Number of training scenes per epoch (>= ``batch_size``).
        val_length: Number of validation scenes.
        test_length: Number of test scenes.
        seed: Family of scenes; each split draws from its own stream.
        prior_images: Training labels used for the pixel-wise priors (None = all).

    >>> dm = StreetScenesDataModule(batch_size=2, num_workers=0, size=(64, 128), val_length=2)
    >>> images, labels = next(iter(dm.val_dataloader()))
    >>> tuple(images.shape), images.dtype, tuple(labels.shape), labels.dtype, dm.label_size
    ((2, 3, 64, 128), torch.uint8, (2, 64, 128), torch.int64, (64, 128))
    """

    def __init__(
        self,
        batch_size: int = TOY.batch_size,
        num_workers: int = TOY.num_workers,
        size: tuple[int, int] = TOY.size,
        train_length: int = TOY.train_length,
        val_length: int = TOY.val_length,
        test_length: int = TOY.test_length,
        seed: int = TOY.seed,
        prior_images: int | None = TOY.prior_images,
    ) -> None:
        super().__init__(batch_size, num_workers, prior_images, eval_batch_size=batch_size)
        if train_length < batch_size:
            raise ValueError(
                f"train_length must be >= batch_size ({batch_size}), since the last partial "
                f"batch is dropped; got {train_length}"
            )
        self.save_hyperparameters()
        self.settings = StreetScenesSettings(
            batch_size, num_workers, size, train_length, val_length, test_length, seed, prior_images
        )

    @property
    def label_size(self) -> tuple[int, int]:
        """(H, W) of labels at evaluation resolution."""
        return int(self.settings.size[0]), int(self.settings.size[1])

    def prior_key(self) -> dict[str, Any]:
        size = [int(s) for s in self.settings.size]
        labels = len(self.prior_labels())
        return {"data": "StreetScenes", "size": size, "seed": self.settings.seed, "labels": labels}

    def make_dataset(self, split: str, augment: bool) -> Dataset[Pair]:
        scenes = self.settings.dataset(split)
        return _Augmented(scenes, v2.RandomHorizontalFlip()) if augment else scenes


class CityscapesDataModule(_SegmentationDataModule):
    """Cityscapes fine annotations (:class:`costseg.data.cityscapes.CityscapesSegmentation`).

    Training uses random scale, padded random crop and horizontal flip; validation and test
    use full-resolution images. Cityscapes' test labels are withheld, so ``test_split``
    defaults to ``"val"``.

    Args:
        root: Folder holding ``leftImg8bit/`` and ``gtFine/``.
        batch_size: Training crops per batch.
        num_workers: Dataloader worker processes.
        crop_size: Training crop (H, W), or one int for a square crop.
        scale_range: Range of the random training scale factor.
        prior_images: Training labels used for the pixel-wise priors (None = all 2975).
        eval_batch_size: Full-resolution images per validation / test batch.
        test_split: Split served by ``test_dataloader``.
    """

    def __init__(
        self,
        root: str = CITYSCAPES.root,
        batch_size: int = CITYSCAPES.batch_size,
        num_workers: int = CITYSCAPES.num_workers,
        crop_size: int | tuple[int, int] = CITYSCAPES.crop_size,
        scale_range: tuple[float, float] = CITYSCAPES.scale_range,
        prior_images: int | None = CITYSCAPES.prior_images,
        eval_batch_size: int = CITYSCAPES.eval_batch_size,
        test_split: str = CITYSCAPES.test_split,
    ) -> None:
        super().__init__(batch_size, num_workers, prior_images, eval_batch_size)
        self.save_hyperparameters()
        self.settings = CityscapesSettings(
            str(root), batch_size, num_workers, crop_size, scale_range, prior_images,
            eval_batch_size, test_split,
        )  # fmt: skip
        self.transform = train_transform(crop_size, scale_range)

    @property
    def label_size(self) -> tuple[int, int]:
        """(H, W) of the first validation label (Cityscapes: 1024 x 2048); reads its header."""
        val = self._dataset("val")
        assert isinstance(val, CityscapesSegmentation)
        with Image.open(val.files[0][1]) as label:
            return label.height, label.width

    def prior_key(self) -> dict[str, Any]:
        root = str(Path(self.settings.root).resolve())
        return {"data": "Cityscapes", "root": root, "labels": len(self.prior_labels())}

    def make_dataset(self, split: str, augment: bool) -> Dataset[Pair]:
        return self.settings.dataset(split, self.transform if augment else None)
