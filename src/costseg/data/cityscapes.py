"""Cityscapes fine annotations as (image, train-id label) pairs, and the training augmentation.

The folder layout is torchvision's ``Cityscapes`` one::

    <root>/leftImg8bit/<split>/<city>/<name>_leftImg8bit.png
    <root>/gtFine/<split>/<city>/<name>_gtFine_labelIds.png
    <root>/gtFine/<split>/<city>/<name>_gtFine_instanceIds.png   (optional: instance metrics)

File pairing is checked when the dataset is built (cheap); the content of each file (decodable,
matching sizes, known label ids) is checked when the item is read, so that opening the 2975
training images does not mean decoding them all.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from PIL import Image
from torch import Tensor
from torch.utils.data import Dataset
from torchvision import tv_tensors
from torchvision.transforms import v2
from torchvision.transforms.v2 import functional as F

from costseg.classes import IGNORE_INDEX, LABEL_ID_TO_TRAIN_ID, VALID_LABEL_IDS

IMAGE_SUFFIX = "_leftImg8bit.png"
LABEL_SUFFIX = "_gtFine_labelIds.png"
INSTANCE_SUFFIX = "_gtFine_instanceIds.png"
_LAYOUT = (
    "expected <root>/leftImg8bit/<split>/<city>/*" + IMAGE_SUFFIX + " and "
    "<root>/gtFine/<split>/<city>/*" + LABEL_SUFFIX + "; Cityscapes is obtained from "
    "https://www.cityscapes-dataset.com after registration (e.g. with csDownload)"
)
_TRAIN_ID = torch.from_numpy(LABEL_ID_TO_TRAIN_ID)
_VALID = torch.zeros(256, dtype=torch.bool)
_VALID[sorted(VALID_LABEL_IDS)] = True

JointTransform = Callable[[tv_tensors.Image, tv_tensors.Mask], tuple[Tensor, Tensor]]


class CityscapesSegmentation(Dataset[tuple[Tensor, Tensor]]):
    """Cityscapes images with their fine labels mapped to the 19 train ids (255 = ignore).

    Args:
        root: Folder holding ``leftImg8bit/`` and ``gtFine/``.
        split: Sub-folder to read, e.g. ``"train"`` or ``"val"``.
        transform: Joint transform called as ``transform(Image, Mask)`` (e.g.
            :func:`train_transform`); None returns the full-resolution pair.

    Attributes:
        files: ``(image_path, label_path)`` per item, sorted by image path.
        names: Item names without suffix (``"frankfurt_000000_000294"``), for writing
            predictions under the same names.
        has_instances: every item has its ``*_gtFine_instanceIds.png`` (:meth:`with_instances`).
        missing_instances: the number of items without one.

    Items are ``(image, label)``: image (3, H, W) uint8 RGB, label (H, W) int64 train ids.

    Raises:
        FileNotFoundError: The root or split folder is missing, holds no images, or an image
            has no label file.

    >>> CityscapesSegmentation("no/such/folder")  # doctest: +ELLIPSIS
    Traceback (most recent call last):
    FileNotFoundError: Cityscapes root 'no/such/folder' does not exist; expected ...
    """

    def __init__(
        self, root: str | Path, split: str = "val", transform: JointTransform | None = None
    ) -> None:
        self.root = Path(root)
        self.split = split
        self.transform = transform
        self.files = _find_pairs(self.root, split)
        self.names = [image.name.removesuffix(IMAGE_SUFFIX) for image, _ in self.files]
        self.instance_files = [
            label.with_name(name + INSTANCE_SUFFIX)
            for (_, label), name in zip(self.files, self.names, strict=True)
        ]
        self.missing_instances = sum(not p.is_file() for p in self.instance_files)
        self.has_instances = self.missing_instances == 0

    def __len__(self) -> int:
        return len(self.files)

    def __getitem__(self, index: int) -> tuple[Tensor, Tensor]:
        image_path, label_path = self.files[index]
        image = _decode(image_path, rgb=True)
        label = self._train_ids(label_path)
        if self.transform is not None:
            if image.shape[-2:] != label.shape:  # training crops image and label together
                image = F.resize(image, list(label.shape), antialias=True)
            image, label = self.transform(tv_tensors.Image(image), tv_tensors.Mask(label))
        return image.as_subclass(Tensor), label.as_subclass(Tensor).long()

    def with_instances(self, index: int) -> tuple[Tensor, Tensor, Tensor]:
        """Item ``index`` (un-augmented) with its (H, W) int64 instance ids, read from the 16-bit
        ``*_gtFine_instanceIds.png`` (``docs/definitions.md §9``)."""
        image_path, label_path = self.files[index]
        image, label = _decode(image_path, rgb=True), self._train_ids(label_path)
        path = self.instance_files[index]
        ids = _decode(path)
        if ids.shape[0] != 1 or ids.shape[-2:] != label.shape:
            raise ValueError(
                f"{path} should be a single-channel instance-id PNG of {tuple(label.shape)} "
                f"(H, W); got {tuple(ids.shape)}"
            )
        return image, label.long(), ids[0].long()

    def read_label(self, index: int) -> Tensor:
        """The un-augmented (H, W) int64 train-id label of item ``index``, without its image."""
        return self._train_ids(self.files[index][1]).long()

    @staticmethod
    def _train_ids(path: Path) -> Tensor:
        """(H, W) uint8 train ids of a label-id PNG; ValueError for unknown ids."""
        ids = _decode(path)
        if ids.dtype != torch.uint8 or ids.shape[0] != 1:
            raise ValueError(
                f"{path} should be a single-channel 8-bit label-id PNG; "
                f"got {ids.shape[0]} channel(s) of {ids.dtype}"
            )
        # A histogram is several times faster than a per-pixel lookup for the check.
        unknown = (torch.bincount(ids.reshape(-1), minlength=256) > 0) & ~_VALID
        if bool(unknown.any()):
            bad = unknown.nonzero().flatten().tolist()
            raise ValueError(f"{path} holds label ids {bad} that are not Cityscapes label ids")
        return _TRAIN_ID.take(ids[0].long())


def _decode(path: Path, rgb: bool = False) -> Tensor:
    """(C, H, W) tensor of an image file (Pillow): RGB with ``rgb``, else the stored channels
    and bit depth (8-bit label ids, 16-bit instance ids); one-line ValueError naming a file
    that cannot be decoded."""
    try:
        with Image.open(path) as image:
            array = np.asarray(image.convert("RGB") if rgb and image.mode != "RGB" else image)
    except (OSError, SyntaxError) as err:  # Pillow: unknown format, truncated or corrupt data
        raise ValueError(f"cannot decode {path}: {err}") from None
    array = array[..., None] if array.ndim == 2 else array
    return torch.from_numpy(array.transpose(2, 0, 1).copy())  # contiguous, writable


def _find_pairs(root: Path, split: str) -> list[tuple[Path, Path]]:
    """Sorted (image, label) paths of a split; FileNotFoundError for anything missing."""
    if not root.is_dir():
        raise FileNotFoundError(f"Cityscapes root '{root}' does not exist; {_LAYOUT}")
    image_dir, label_dir = root / "leftImg8bit" / split, root / "gtFine" / split
    for folder in (image_dir, label_dir):
        if not folder.is_dir():
            raise FileNotFoundError(f"Cityscapes split folder '{folder}' does not exist; {_LAYOUT}")
    images = sorted(image_dir.glob("*/*" + IMAGE_SUFFIX))
    if not images:
        raise FileNotFoundError(f"no *{IMAGE_SUFFIX} files in '{image_dir}/<city>/'; {_LAYOUT}")
    pairs = []
    for image in images:
        name = image.name.removesuffix(IMAGE_SUFFIX)
        label = label_dir / image.parent.name / (name + LABEL_SUFFIX)
        if not label.is_file():
            raise FileNotFoundError(f"image {image} has no label file; expected {label}")
        pairs.append((image, label))
    return pairs


class RandomScale(v2.Transform):
    """Resize image and mask by one factor drawn uniformly from ``scale_range``.

    Images are resized bilinearly (antialiased), masks with nearest neighbour (torchvision
    dispatches on ``tv_tensors.Mask``).
    """

    def __init__(self, scale_range: tuple[float, float]) -> None:
        super().__init__()
        self.scale_range = scale_range

    def make_params(self, flat_inputs: list[Any]) -> dict[str, Any]:
        height, width = F.get_size(flat_inputs[0])
        low, high = self.scale_range
        scale = low + (high - low) * torch.rand(()).item()
        return {"size": [max(1, round(height * scale)), max(1, round(width * scale))]}

    def transform(self, inpt: Any, params: dict[str, Any]) -> Any:
        return self._call_kernel(F.resize, inpt, size=params["size"], antialias=True)


def train_transform(
    crop_size: int | Sequence[int], scale_range: tuple[float, float] = (0.5, 2.0)
) -> v2.Compose:
    """Training augmentation: random scale, random crop (padded), random horizontal flip.

    Padding fills the image with 0 and the mask with 255 (ignored), so crops larger than the
    scaled image keep their size without inventing labels.

    Args:
        crop_size: Output (H, W), or one int for a square crop.
        scale_range: ``(low, high)`` range of the random scale factor, ``0 < low <= high``.

    >>> t = train_transform((4, 6), scale_range=(1.0, 1.0))
    >>> image, mask = t(tv_tensors.Image(torch.zeros(3, 2, 3, dtype=torch.uint8)),
    ...                 tv_tensors.Mask(torch.zeros(2, 3, dtype=torch.uint8)))
    >>> tuple(image.shape), tuple(mask.shape), int((mask == 255).sum())
    ((3, 4, 6), (4, 6), 18)
    """
    size = [crop_size, crop_size] if isinstance(crop_size, int) else list(crop_size)
    if len(size) != 2 or min(size) < 1:
        raise ValueError(f"crop_size must be a positive int or (H, W); got {crop_size!r}")
    low, high = scale_range
    if not 0 < low <= high:
        raise ValueError(f"scale_range must satisfy 0 < low <= high; got {scale_range!r}")
    return v2.Compose(
        [
            RandomScale((low, high)),
            v2.RandomCrop(
                size, pad_if_needed=True, fill={tv_tensors.Image: 0, tv_tensors.Mask: IGNORE_INDEX}
            ),
            v2.RandomHorizontalFlip(),
        ]
    )
