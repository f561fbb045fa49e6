"""CityscapesSegmentation on a generated tree, its errors, and the training transform."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import (
    CITYSCAPES_FILES,
    CITYSCAPES_SIZE,
    cityscapes_image,
    cityscapes_label_ids,
    write_cityscapes_item,
)
from PIL import Image
from torchvision import tv_tensors
from torchvision.transforms import v2

from costseg.data.cityscapes import CityscapesSegmentation, train_transform

# Hand-written from the Cityscapes label table (label id → train id).
EXPECTED = {7: 0, 8: 1, 11: 2, 21: 8, 23: 10, 24: 11, 26: 13, 33: 18, 255: 255}
EXPECTED |= {i: 255 for i in (0, 1, 2, 3, 4, 5, 6, 9, 10, 14, 15, 16, 29, 30)}


def test_loads_sorted_pairs_with_train_ids(cityscapes_root: Path) -> None:
    ds = CityscapesSegmentation(cityscapes_root, split="val")
    assert len(ds) == 3
    assert ds.names == CITYSCAPES_FILES["val"]
    image_path, label_path = ds.files[0]
    assert image_path.relative_to(cityscapes_root).as_posix() == (
        "leftImg8bit/val/frankfurt/frankfurt_000000_000294_leftImg8bit.png"
    )
    assert label_path.relative_to(cityscapes_root).as_posix() == (
        "gtFine/val/frankfurt/frankfurt_000000_000294_gtFine_labelIds.png"
    )
    for index in range(len(ds)):
        image, label = ds[index]
        assert image.shape == (3, *CITYSCAPES_SIZE) and image.dtype == torch.uint8
        assert label.shape == CITYSCAPES_SIZE and label.dtype == torch.int64
        ids = cityscapes_label_ids(index)
        assert np.array_equal(image.numpy(), cityscapes_image(ids))
        for label_id, train_id in EXPECTED.items():
            assert (label[torch.from_numpy(ids == label_id)] == train_id).all(), label_id
        assert torch.equal(ds.read_label(index), label)
        assert set(label.unique().tolist()) == {*range(19), 255}


def _message(excinfo: pytest.ExceptionInfo) -> str:
    message = str(excinfo.value)
    assert "\n" not in message
    return message


def test_missing_root_and_split(cityscapes_root: Path, tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError) as excinfo:
        CityscapesSegmentation(tmp_path / "nowhere")
    message = _message(excinfo)
    assert "nowhere" in message and "https://www.cityscapes-dataset.com" in message
    assert "leftImg8bit/<split>/<city>" in message and "csDownload" in message
    with pytest.raises(FileNotFoundError, match=r"leftImg8bit/test"):
        CityscapesSegmentation(cityscapes_root, split="test")
    shutil.rmtree(cityscapes_root / "gtFine" / "val")
    with pytest.raises(FileNotFoundError, match=r"gtFine/val"):
        CityscapesSegmentation(cityscapes_root, split="val")


def test_image_without_label(cityscapes_root: Path) -> None:
    label = cityscapes_root / "gtFine/val/lindau/lindau_000000_000019_gtFine_labelIds.png"
    label.unlink()
    with pytest.raises(FileNotFoundError) as excinfo:
        CityscapesSegmentation(cityscapes_root, split="val")
    assert "lindau_000000_000019_leftImg8bit.png" in _message(excinfo)


def test_images_of_another_size_than_their_labels(cityscapes_root: Path) -> None:
    """Read as they are; a training transform crops them together with the label after the image
    is resized to the label's size."""
    ds = CityscapesSegmentation(cityscapes_root, split="val")
    Image.open(ds.files[1][0]).resize((32, 16)).save(ds.files[1][0])
    image, label = ds[1]
    assert image.shape == (3, 16, 32) and label.shape == (32, 64)
    crop = CityscapesSegmentation(cityscapes_root, "val", train_transform((32, 64), (1.0, 1.0)))
    image, label = crop[1]
    assert image.shape == (3, 32, 64) and label.shape == (32, 64)


def test_unknown_label_ids(cityscapes_root: Path) -> None:
    ds = CityscapesSegmentation(cityscapes_root, split="val")
    ids = torch.from_numpy(cityscapes_label_ids(2))
    ids[0, :2] = torch.tensor([40, 34])
    Image.fromarray(ids.numpy()).save(ds.files[2][1])
    with pytest.raises(ValueError) as excinfo:
        ds[2]
    message = _message(excinfo)
    assert "lindau_000000_000019_gtFine_labelIds.png" in message and "[34, 40]" in message


def test_corrupt_and_wrong_format_files(cityscapes_root: Path) -> None:
    ds = CityscapesSegmentation(cityscapes_root, split="val")
    ds.files[0][0].write_bytes(b"not a png")
    ds.files[1][1].write_bytes(ds.files[1][1].read_bytes()[:60])  # truncated
    Image.fromarray(np.zeros((*CITYSCAPES_SIZE, 3), np.uint8)).save(ds.files[2][1])  # RGB
    for index, path in enumerate([ds.files[0][0], ds.files[1][1], ds.files[2][1]]):
        with pytest.raises(ValueError) as excinfo:
            ds[index]
        message = _message(excinfo)
        assert str(path) in message and ".cpp" not in message


def test_extra_item_keeps_sorted_order(cityscapes_root: Path) -> None:
    write_cityscapes_item(cityscapes_root, "val", "bielefeld_000000_000321", 5)
    ds = CityscapesSegmentation(cityscapes_root, split="val")
    assert ds.names == ["bielefeld_000000_000321", *CITYSCAPES_FILES["val"]]
    assert torch.equal(ds.read_label(0), ds[0][1])


def _encoded_pair(h: int = 32, w: int = 64, block: int = 8) -> tuple[torch.Tensor, torch.Tensor]:
    """Asymmetric blocks of train ids 0..18 (no 255); image value = 10 * train id + 5."""
    rows = torch.arange(h)[:, None] // block
    cols = torch.arange(w)[None, :] // block
    label = ((rows * 7 + cols * cols) % 19).to(torch.uint8)
    return (label * 10 + 5).expand(3, h, w).clone(), label


def _transform(
    transform: v2.Transform, image: torch.Tensor, label: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    out_image, out_label = transform(tv_tensors.Image(image), tv_tensors.Mask(label))
    return out_image.as_subclass(torch.Tensor), out_label.as_subclass(torch.Tensor)


def _constant_around(label: torch.Tensor, radius: int) -> torch.Tensor:
    """(H, W) bool: the label is constant in the (2 radius + 1)² window around the pixel.

    The crop border is excluded: its image pixels were blended with pixels outside the crop.
    """
    x = label[None, None].float()
    high = torch.nn.functional.max_pool2d(x, 2 * radius + 1, stride=1)
    low = -torch.nn.functional.max_pool2d(-x, 2 * radius + 1, stride=1)
    return torch.nn.functional.pad((high == low)[0, 0], [radius] * 4, value=False)


def test_train_transform_crop_flip_exact_alignment() -> None:
    torch.manual_seed(0)
    image, label = _encoded_pair()
    transform = train_transform((24, 40), scale_range=(1.0, 1.0))
    flipped = 0
    for _ in range(20):
        out_image, out_label = _transform(transform, image, label)
        assert out_image.shape == (3, 24, 40) and out_label.shape == (24, 40)
        assert torch.equal(out_image[0], out_label * 10 + 5)
        # Find the crop in the original (or its mirror): the label must be an exact window.
        windows = [label, label.flip(-1)]
        found = [
            any(
                torch.equal(src[y : y + 24, x : x + 40], out_label)
                for y in range(9)
                for x in range(25)
            )
            for src in windows
        ]
        assert any(found)
        flipped += found[1] and not found[0]
    assert 0 < flipped < 20


def test_train_transform_scale_and_padding() -> None:
    torch.manual_seed(1)
    image, label = _encoded_pair()
    out_image, out_label = _transform(train_transform((80, 150), (2.0, 2.0)), image, label)
    assert out_label.shape == (80, 150)
    assert int((out_label != 255).sum()) == 64 * 128  # the whole 2x image, padded
    assert ((out_label == 255) == (out_image == 0).all(dim=0)).all()
    torch.manual_seed(2)
    image, label = _encoded_pair(64, 128, block=16)
    for _ in range(10):
        out_image, out_label = _transform(train_transform(48, (0.5, 2.0)), image, label)
        assert out_label.shape == (48, 48) and out_image.shape == (3, 48, 48)
        assert set(out_label.unique().tolist()) <= {*range(19), 255}
        # Bilinear resizing blends image values near block edges only: compare block interiors.
        interior = _constant_around(out_label, radius=2) & (out_label != 255)
        assert interior.sum() > 100
        assert torch.equal(out_image[0][interior], out_label[interior] * 10 + 5)


def test_train_transform_rejects_bad_arguments() -> None:
    with pytest.raises(ValueError, match="crop_size"):
        train_transform(0)
    with pytest.raises(ValueError, match="scale_range"):
        train_transform(32, (2.0, 1.0))
