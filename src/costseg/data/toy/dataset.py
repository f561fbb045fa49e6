"""Procedural street scenes: the project's embedded default dataset (nothing to download).

Each scene is a dash-cam view of a street in perspective: road with lane markings, sidewalks,
terrain, facades with windows, a little sky, poles with signs and lights, vehicles, persons and
riders at many depths. Labels are the 19 Cityscapes train ids (255 = ignore) with roughly
Cityscapes' class frequencies and layout. Images get texture noise, haze, shadows, per-scene
lighting and blur, so that small, far and occluded objects stay genuinely uncertain.

>>> image, label = StreetScenes(split="val", length=2, size=(64, 128))[0]
>>> image.shape, image.dtype, label.shape, label.dtype
(torch.Size([3, 64, 128]), torch.uint8, torch.Size([64, 128]), torch.int64)
"""

from __future__ import annotations

import numpy as np
import torch
from PIL import Image, ImageDraw
from torch.utils.data import Dataset

from costseg.classes import IGNORE_INDEX, TRAIN_ID_TO_LABEL_ID
from costseg.data.toy.anomalies import draw_anomalies
from costseg.data.toy.draw import SKY, Canvas
from costseg.data.toy.instances import InstanceLayer
from costseg.data.toy.photo import photograph
from costseg.data.toy.scene import draw_street
from costseg.data.toy.street import Street

MIN_SIZE = 64
SPLITS = {"train": 0, "val": 1, "test": 2}
LABEL_ID_SKY = TRAIN_ID_TO_LABEL_ID[SKY]


def _check_size(size: tuple[int, int]) -> tuple[int, int]:
    ok = len(size) == 2 and all(isinstance(s, (int, np.integer)) for s in size)
    if not ok or min(size) < MIN_SIZE:
        raise ValueError(f"size must be (height, width) integers >= {MIN_SIZE}; got {size!r}")
    return int(size[0]), int(size[1])


def render_scene(
    rng: np.random.Generator, size: tuple[int, int] = (256, 512)
) -> tuple[np.ndarray, np.ndarray]:
    """Render one street scene, a pure function of the generator's state.

    Args:
        rng: the source of all randomness.
        size: (H, W) in pixels, each >= 64; the geometry scales with it.

    Returns:
        image (H, W, 3) uint8 RGB and label (H, W) uint8 train ids 0..18, 255 = ignore.

    >>> image, label = render_scene(np.random.default_rng(0), size=(64, 128))
    >>> image.shape, label.shape, label.dtype.name
    ((64, 128, 3), (64, 128), 'uint8')
    """
    image, label, _, _ = _render(rng, size, instances=False)
    return image, label


def _render(
    rng: np.random.Generator,
    size: tuple[int, int],
    instances: bool,
    anomalies: np.random.Generator | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, np.ndarray | None]:
    """Image, label, instance ids (or None) and, with an ``anomalies`` generator, the anomaly
    mask (or None); the unknown objects come from a generator of their own, so the scene
    around them is the one rendered without them."""
    h, w = _check_size(size)
    st = Street.sample(rng, h, w)
    image, label = st.sky_gradient(h, w), Image.new("L", (w, h), SKY)
    layer = InstanceLayer(Image.new("I", (w, h), int(LABEL_ID_SKY))) if instances else None
    shadow = Image.new("L", (w, h), 0)
    canvas = Canvas(image, label, st.cam, st.sky[1], st.haze_range, layer)
    draw_street(canvas, rng, st, ImageDraw.Draw(shadow))
    mask = None
    if anomalies is not None:
        marks = Image.new("L", (w, h), 0)
        draw_anomalies(canvas, anomalies, st, ImageDraw.Draw(marks))
        mask = np.array(marks)
    labels = np.array(label)
    if mask is not None:
        mask = np.where(mask == 1, 1, np.where(labels == IGNORE_INDEX, IGNORE_INDEX, 0))
    ids = None if layer is None else layer.array()
    return photograph(image, labels, shadow, rng), labels, ids, mask


class StreetScenes(Dataset):
    """Procedural street scenes as a map-style dataset, deterministic per (seed, split, index).

    Args:
        split: "train", "val" or "test"; each draws from its own random stream.
        length: number of scenes.
        size: (H, W) of every image, each >= 64.
        seed: non-negative integer choosing the whole family of scenes.
        anomalies: add one to three unknown objects to every scene (the same scenes around
            them; docs/definitions.md §17), labelled 255; :meth:`with_anomalies` gives the mask.

    Items are ``(image, label)``: (3, H, W) uint8 RGB and (H, W) int64 train ids (255 = ignore).

    >>> a, b = StreetScenes("val", 3, (64, 128))[2], StreetScenes("val", 3, (64, 128))[-1]
    >>> bool((a[0] == b[0]).all() and (a[1] == b[1]).all())
    True
    """

    def __init__(
        self,
        split: str = "train",
        length: int = 1000,
        size: tuple[int, int] = (256, 512),
        seed: int = 0,
        anomalies: bool = False,
    ) -> None:
        if split not in SPLITS:
            raise ValueError(f"split must be one of {sorted(SPLITS)}; got {split!r}")
        for name, value in (("length", length), ("seed", seed)):
            if not isinstance(value, (int, np.integer)) or value < 0:
                raise ValueError(f"{name} must be a non-negative integer; got {value!r}")
        self.split, self.length, self.size, self.seed = (
            split,
            int(length),
            _check_size(size),
            int(seed),
        )
        self.anomalies = bool(anomalies)

    def __len__(self) -> int:
        return self.length

    has_instances = True
    """Every scene has instance ids (:meth:`with_instances`)."""

    def __getitem__(self, index: int) -> tuple[torch.Tensor, torch.Tensor]:
        image, label, _, _ = self._item(index, instances=False)
        return image, label

    @property
    def has_anomalies(self) -> bool:
        """Every scene holds unknown objects (:meth:`with_anomalies`)."""
        return self.anomalies

    def with_anomalies(
        self, index: int
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """Item ``index`` with its instance ids and its (H, W) int64 anomaly mask: 1 = unknown
        object, 0 = a known class, 255 = ignored (SegmentMeIfYouCan's encoding;
        ``docs/definitions.md §17``).

        >>> scenes = StreetScenes("val", 1, (64, 128), anomalies=True)
        >>> _, label, _, mask = scenes.with_anomalies(0)
        >>> bool((mask == 1).any()), bool((label[mask == 1] == 255).all())
        (True, True)
        """
        if not self.anomalies:
            raise ValueError("these scenes hold no unknown objects: StreetScenes(anomalies=True)")
        image, label, ids, mask = self._item(index, instances=True)
        assert ids is not None and mask is not None
        return image, label, ids, mask

    def with_instances(self, index: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Item ``index`` with its (H, W) int64 instance ids (``docs/definitions.md §9``).

        >>> _, label, ids = StreetScenes("val", 1, (64, 128)).with_instances(0)
        >>> ids.shape, ids.dtype, bool((ids >= 1000).any())
        (torch.Size([64, 128]), torch.int64, True)
        """
        image, label, ids, _ = self._item(index, instances=True)
        assert ids is not None
        return image, label, ids

    def _item(self, index: int, instances: bool) -> tuple[torch.Tensor, ...]:
        if not -self.length <= index < self.length:
            raise IndexError(f"index {index} is out of range for {self.length} scenes")
        key = [self.seed, SPLITS[self.split], int(index) % self.length]
        unknown = np.random.default_rng([*key, 1]) if self.anomalies else None
        image, label, ids, mask = _render(np.random.default_rng(key), self.size, instances, unknown)
        image_t = torch.from_numpy(image).permute(2, 0, 1).contiguous()
        return image_t, _int64(label), _int64(ids), _int64(mask)


def _int64(array: np.ndarray | None) -> torch.Tensor | None:
    return None if array is None else torch.from_numpy(array.astype(np.int64))
