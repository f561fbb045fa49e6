"""Both LightningDataModules: batches, loader settings and the labels used for priors."""

from __future__ import annotations

import gc
import os
from pathlib import Path

import pytest
import torch
from conftest import CITYSCAPES_SIZE
from pid_items import PidItems

from costseg.classes import CLASS_NAMES
from costseg.data.cityscapes import CityscapesSegmentation
from costseg.data.datamodule import CityscapesDataModule, StreetScenesDataModule

SIZE = (64, 128)


def _check_batch(batch: list[torch.Tensor], n: int, size: tuple[int, int]) -> None:
    images, labels = batch
    assert images.shape == (n, 3, *size) and images.dtype == torch.uint8
    assert labels.shape == (n, *size) and labels.dtype == torch.int64
    assert set(labels.unique().tolist()) <= {*range(19), 255}


@pytest.fixture(scope="module")
def toy() -> StreetScenesDataModule:
    return StreetScenesDataModule(
        batch_size=2, num_workers=0, size=SIZE, train_length=5, val_length=3, test_length=2,
        prior_images=4,
    )  # fmt: skip


def test_toy_batches(toy: StreetScenesDataModule) -> None:
    assert toy.num_classes == 19 and toy.class_names == CLASS_NAMES and toy.label_size == SIZE
    toy.setup("fit")
    train = list(toy.train_dataloader())
    assert len(train) == 2  # 5 scenes, last partial batch dropped
    _check_batch(train[0], 2, SIZE)
    val = list(toy.val_dataloader())
    assert [len(b[0]) for b in val] == [2, 1]
    _check_batch(val[0], 2, SIZE)
    _check_batch(next(iter(toy.test_dataloader())), 2, SIZE)


def test_toy_train_is_flipped_scenes(toy: StreetScenesDataModule) -> None:
    plain = toy.make_dataset("train", augment=False)
    augmented = toy.make_dataset("train", augment=True)
    torch.manual_seed(0)
    flips = 0
    for _ in range(4):
        for index in range(len(plain)):
            (image, label), (aug_image, aug_label) = plain[index], augmented[index]
            flipped = torch.equal(aug_label, label.flip(-1))
            assert flipped or torch.equal(aug_label, label)
            assert torch.equal(aug_image, image.flip(-1) if flipped else image)
            flips += flipped and not torch.equal(label, label.flip(-1))
    assert 0 < flips < 4 * len(plain)


def test_toy_prior_labels(toy: StreetScenesDataModule) -> None:
    labels = list(toy.prior_labels())
    assert len(labels) == len(toy.prior_labels()) == 4
    plain = toy.make_dataset("train", augment=False)
    for index, label in enumerate(labels):
        assert torch.equal(label, plain[index][1])
    everything = StreetScenesDataModule(batch_size=2, size=SIZE, train_length=3, prior_images=None)
    assert len(everything.prior_labels()) == 3


def _epoch(loader) -> tuple[set[int], list[list[int]], list[bool]]:
    """The reading processes, the batches' indices, and whether each batch was pinned."""
    batches = list(loader)
    return (
        {pid for pids, _ in batches for pid in pids.tolist()},
        [indices.tolist() for _, indices in batches],
        [pids.is_pinned() for pids, _ in batches],
    )


@pytest.mark.workers
@pytest.mark.parametrize("workers", [0, 2])
def test_loader_settings(monkeypatch, workers: int) -> None:
    """Training drops the last partial batch and shuffles; evaluation keeps every item in
    order; worker processes read the items and survive the epoch; pinned only with CUDA."""
    data = StreetScenesDataModule(batch_size=2, num_workers=workers, size=SIZE, train_length=5)
    monkeypatch.setattr(data, "make_dataset", lambda split, augment: PidItems(5))
    readers, train, pinned = _epoch(shuffled := data.train_dataloader())
    assert [len(b) for b in train] == [2, 2] and len({i for b in train for i in b}) == 4
    assert set(pinned) == {torch.cuda.is_available()}
    readers_val, val, _ = _epoch(loader := data.val_dataloader())
    assert val == [[0, 1], [2, 3], [4]]
    orders = {tuple(i for b in _epoch(shuffled)[1] for i in b) for _ in range(4)}
    assert len(orders) > 1  # shuffled: 4 equal epochs have a chance of 1 in 120³
    if workers == 0:
        assert readers == readers_val == {os.getpid()}
        return
    assert os.getpid() not in readers | readers_val and len(readers_val) == workers
    assert _epoch(loader)[0] == readers_val  # the same processes: persistent workers
    del shuffled, loader
    gc.collect()  # their workers stop here, not whenever a later test collects them


def test_bad_arguments() -> None:
    with pytest.raises(ValueError, match="batch_size"):
        StreetScenesDataModule(batch_size=0)
    with pytest.raises(ValueError, match="num_workers"):
        StreetScenesDataModule(num_workers=-1)
    with pytest.raises(ValueError, match="prior_images"):
        CityscapesDataModule(prior_images=0)
    with pytest.raises(ValueError, match="train_length"):
        StreetScenesDataModule(batch_size=8, train_length=4)
    with pytest.raises(ValueError, match="crop_size"):
        CityscapesDataModule(crop_size=0)


def test_cityscapes_batches(cityscapes_root: Path) -> None:
    dm = CityscapesDataModule(
        root=str(cityscapes_root), batch_size=2, num_workers=0, crop_size=(16, 24),
        eval_batch_size=3,
    )  # fmt: skip
    assert dm.num_classes == 19 and dm.label_size == CITYSCAPES_SIZE
    dm.setup("fit")
    train = list(dm.train_dataloader())
    assert len(train) == 1
    _check_batch(train[0], 2, (16, 24))
    _check_batch(next(iter(dm.val_dataloader())), 3, CITYSCAPES_SIZE)
    test = next(iter(dm.test_dataloader()))  # Cityscapes' test labels are withheld: val
    val = CityscapesSegmentation(cityscapes_root, "val")
    assert torch.equal(test[1][0], val[0][1])


def test_cityscapes_prior_labels(cityscapes_root: Path) -> None:
    dm = CityscapesDataModule(root=str(cityscapes_root), num_workers=0)
    train = CityscapesSegmentation(cityscapes_root, "train")
    labels = list(dm.prior_labels())
    assert len(labels) == 3
    for index, label in enumerate(labels):
        assert torch.equal(label, train[index][1])
    two = CityscapesDataModule(str(cityscapes_root), num_workers=1, prior_images=2)
    labels = list(two.prior_labels())  # read in a worker process
    assert len(labels) == 2 and torch.equal(labels[1], train[1][1])


def test_cityscapes_missing_root(tmp_path: Path) -> None:
    dm = CityscapesDataModule(root=str(tmp_path / "none"))
    with pytest.raises(FileNotFoundError, match=r"cityscapes-dataset\.com"):
        dm.setup("fit")


@pytest.mark.parametrize(
    ("module", "class_path"),
    [
        (StreetScenesDataModule, "costseg.data.datamodule.StreetScenesDataModule"),
        (CityscapesDataModule, "costseg.data.datamodule.CityscapesDataModule"),
    ],
)
def test_training_and_evaluation_share_the_data_defaults(module, class_path: str) -> None:
    """Evaluation reads a checkpoint's data configuration without Lightning: a datamodule's
    defaults (every argument of its signature) are the settings evaluation fills in."""
    import dataclasses
    import inspect

    from costseg.data.from_config import data_settings

    settings = data_settings({"class_path": class_path, "init_args": {}})
    defaults = {
        name: p.default
        for name, p in inspect.signature(module.__init__).parameters.items()
        if name != "self"
    }
    assert defaults == dataclasses.asdict(settings)


def test_evaluation_builds_the_datasets_training_validates_on(cityscapes_root: Path) -> None:
    from costseg.data.from_config import build_dataset, data_settings

    config = {"class_path": "x.StreetScenesDataModule", "init_args": {"size": [64, 128]}}
    toy = StreetScenesDataModule(size=(64, 128), val_length=3)
    built = build_dataset({**config, "init_args": {"size": [64, 128], "val_length": 3}}, "val")
    assert len(built) == len(toy.make_dataset("val", augment=False)) == 3
    assert torch.equal(built[2][0], toy.make_dataset("val", augment=False)[2][0])
    settings = data_settings(config)
    assert (settings.eval_batch_size, settings.num_workers) == (
        toy.eval_batch_size,
        toy.num_workers,
    )
    city = data_settings({}, root=cityscapes_root)
    dm = CityscapesDataModule(root=str(cityscapes_root))
    assert (city.eval_batch_size, city.num_workers) == (dm.eval_batch_size, dm.num_workers)
    assert build_dataset({}, "test", cityscapes_root).files == dm.make_dataset("test", False).files
    with pytest.raises(ValueError, match="unknown dataset"):
        data_settings({"class_path": "x.Other"})
    with pytest.raises(ValueError, match="unexpected keyword argument 'sizes'"):
        data_settings({**config, "init_args": {"sizes": [1, 2]}})
