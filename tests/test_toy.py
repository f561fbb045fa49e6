"""Tests of the procedural street scenes (costseg.data.toy.dataset)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from costseg.classes import CLASS_NAMES, IGNORE_INDEX, NUM_CLASSES, class_index
from costseg.data.toy import StreetScenes, render_scene
from costseg.data.toy.draw import Camera

SIZE = (128, 256)
# Cityscapes' pixel frequencies (%), over labelled pixels of the fine training annotations.
CITYSCAPES = {
    "road": 36.9,
    "building": 22.8,
    "vegetation": 15.9,
    "car": 7.0,
    "sidewalk": 6.1,
    "sky": 4.0,
    "person": 1.2,
}


@pytest.fixture(scope="module")
def labels() -> np.ndarray:
    """(300, H, W) uint8 labels of the first 300 training scenes."""
    ds = StreetScenes(split="train", length=300, size=SIZE, seed=0)
    return np.stack([ds[i][1].numpy().astype(np.uint8) for i in range(len(ds))])


def test_items_have_the_documented_types_and_shapes() -> None:
    image, label = StreetScenes(split="test", length=1, size=(96, 160))[0]
    assert image.shape == (3, 96, 160) and image.dtype == torch.uint8
    assert label.shape == (96, 160) and label.dtype == torch.int64
    image_np, label_np = render_scene(np.random.default_rng(3), size=(256, 512))
    assert image_np.shape == (256, 512, 3) and image_np.dtype == np.uint8
    assert label_np.shape == (256, 512) and label_np.dtype == np.uint8


def test_same_seed_split_index_gives_the_same_scene_and_streams_differ() -> None:
    def item(split: str, index: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
        image, label = StreetScenes(split=split, length=5, size=(64, 128), seed=seed)[index]
        return image.numpy(), label.numpy()

    a, b = item("val", 3), item("val", 3)
    assert np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1])
    assert np.array_equal(item("val", -2)[1], a[1])  # negative indices as for a list
    # render_scene is the same pure function of the generator
    image, label = render_scene(np.random.default_rng([0, 1, 3]), size=(64, 128))
    assert np.array_equal(image.transpose(2, 0, 1), a[0]) and np.array_equal(label, a[1])
    for other in (item("train", 3), item("test", 3), item("val", 4), item("val", 3, seed=1)):
        assert not np.array_equal(other[1], a[1])


def test_label_values_are_train_ids_or_ignore(labels: np.ndarray) -> None:
    values = set(np.unique(labels).tolist())
    assert values <= set(range(NUM_CLASSES)) | {IGNORE_INDEX}
    assert (labels == IGNORE_INDEX).mean() < 0.05  # a hood strip, rails, clutter: a few pixels


def test_every_class_occurs(labels: np.ndarray) -> None:
    present = np.bincount(labels.ravel(), minlength=256)[:NUM_CLASSES] > 0
    assert present.all(), [n for n, p in zip(CLASS_NAMES, present, strict=True) if not p]


def test_class_frequencies_are_within_a_factor_two_of_cityscapes(labels: np.ndarray) -> None:
    freq = np.zeros(NUM_CLASSES)
    for label in labels[:200]:
        valid = label[label != IGNORE_INDEX]
        freq += np.bincount(valid, minlength=NUM_CLASSES)[:NUM_CLASSES] / valid.size
    freq *= 100.0 / 200
    for name, reference in CITYSCAPES.items():
        assert reference / 2 <= freq[class_index(name)] <= 2 * reference, (name, freq)


def test_layout_priors_put_each_region_where_cityscapes_has_it(labels: np.ndarray) -> None:
    """Per-pixel most frequent class among road, sidewalk, building and sky (the paper's RoIs)."""
    ids = [class_index(n) for n in ("road", "sidewalk", "building", "sky")]
    counts = np.stack([(labels == c).sum(axis=0) for c in ids])
    roi = np.array(ids)[counts.argmax(axis=0)]
    h, w = SIZE
    road, sidewalk, building, sky = ids
    assert roi[h - 5, w // 2] == road
    assert roi[2, w // 2] == sky
    assert roi[h // 5, w // 10] == building and roi[h // 5, w - w // 10] == building
    lower = roi[h // 3 :]
    assert (lower[:, : w // 3] == sidewalk).any() and (lower[:, -w // 3 :] == sidewalk).any()


def test_roi_map_of_the_default_priors_has_sidewalk_on_both_sides(labels: np.ndarray) -> None:
    """With the default smoothing, the sidewalk RoI (id 2) reaches both halves of the image."""
    from costseg.data.priors import pixel_priors, roi_map

    roi = roi_map(pixel_priors(torch.from_numpy(labels).long(), progress=False))
    half = SIZE[1] // 2
    assert (roi[:, :half] == 2).any() and (roi[:, half:] == 2).any()
    assert {1, 2, 3, 4} <= set(roi.unique().tolist())


def test_camera_projects_by_hand() -> None:
    cam = Camera(f=100.0, cx=50.0, hy=40.0, hc=1.5)
    assert cam.p(1.0, 0.0, 10.0) == pytest.approx((60.0, 55.0))  # ground point right ahead
    assert cam.p(-2.0, 1.5, 20.0) == pytest.approx((40.0, 40.0))  # at eye height: the horizon


def test_bad_arguments_raise_value_error() -> None:
    with pytest.raises(ValueError, match="split"):
        StreetScenes(split="training")
    with pytest.raises(ValueError, match="64"):
        StreetScenes(size=(32, 512))
    with pytest.raises(ValueError, match="size"):
        render_scene(np.random.default_rng(0), size=(128,))  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="length"):
        StreetScenes(length=-1)
    with pytest.raises(ValueError, match="seed"):
        StreetScenes(seed=-3)


def test_length_and_index_error() -> None:
    ds = StreetScenes(split="val", length=4, size=(64, 64))
    assert len(ds) == 4
    with pytest.raises(IndexError):
        ds[4]
    with pytest.raises(IndexError):
        ds[-5]
