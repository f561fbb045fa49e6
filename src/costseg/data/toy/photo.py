"""Photographic look of the procedural street scenes.

:func:`photograph` turns a drawn scene into a camera-like image: soft cast shadows,
class-dependent texture noise, per-scene exposure, colour cast and gamma, then lens blur.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np
from PIL import Image, ImageFilter

from costseg.classes import IGNORE_INDEX, class_index

# Texture amplitude per train id (1/16 of the noise bank's unit) of fine grain, leaf-sized blobs
# and large blotches: part of each class's characteristic look.
_AMP = np.zeros((3, 256), dtype=np.int16)
_AMP[:, IGNORE_INDEX] = (8, 4, 8)
for _name, _amp in {
    "road": (7, 0, 5), "sidewalk": (8, 2, 5), "building": (5, 0, 8), "wall": (8, 3, 12),
    "fence": (6, 0, 4), "pole": (3, 0, 2), "traffic light": (2, 0, 0), "traffic sign": (2, 0, 0),
    "vegetation": (12, 22, 10), "terrain": (10, 12, 14), "sky": (1, 0, 7),
    "person": (4, 0, 3), "rider": (4, 0, 3), "car": (3, 0, 3), "truck": (4, 0, 4),
    "bus": (3, 0, 3), "train": (3, 0, 3), "motorcycle": (4, 0, 2), "bicycle": (4, 0, 2),
}.items():  # fmt: skip
    _AMP[:, class_index(_name)] = _amp


@lru_cache(maxsize=4)
def _noise_bank(h: int, w: int) -> tuple[np.ndarray, ...]:
    """Fixed (2h, 2w) int16 noise fields (grain, leaves, blotches) that scenes crop at random.

    Fresh Gaussian noise per image would dominate the generation time; a fixed bank cropped at
    per-scene offsets is as varied for a network and keeps every scene deterministic.
    """
    rng = np.random.default_rng(20190616)
    fields = [rng.normal(0.0, 16.0, (2 * h, 2 * w))]
    for cell in (max(2, h // 90), max(4, h // 16)):
        small = rng.normal(0.0, 1.0, (2 * h // cell + 1, 2 * w // cell + 1)).astype(np.float32)
        big = np.asarray(Image.fromarray(small, mode="F").resize((2 * w, 2 * h), Image.BILINEAR))
        fields.append(big * (16.0 / big.std()))
    return tuple(np.clip(f, -127, 127).astype(np.int16) for f in fields)


def _texture(rgb: np.ndarray, label: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Add class-dependent texture noise to the (H, W, 3) uint8 image."""
    h, w = label.shape
    noise = np.zeros((h, w), dtype=np.int16)
    for amp, field in zip(
        (_AMP * rng.uniform(0.6, 1.4)).astype(np.int16), _noise_bank(h, w), strict=True
    ):
        y, x = rng.integers(0, h + 1), rng.integers(0, w + 1)
        noise += amp[label] * field[y : y + h, x : x + w]
    noise >>= 4
    return np.clip(rgb.astype(np.int16) + noise[..., None], 0, 255).astype(np.uint8)


def photograph(
    image: Image.Image, label: np.ndarray, shadow: Image.Image, rng: np.random.Generator
) -> np.ndarray:
    """Soft shadows, texture, per-scene exposure, colour cast and gamma, then lens blur."""
    h = label.shape[0]
    if shadow.getbbox():
        dark = image.point((np.arange(256) * rng.uniform(0.45, 0.7)).astype(int).tolist() * 3)
        image = Image.composite(dark, image, shadow.filter(ImageFilter.BoxBlur(h / 200)))
    image = Image.fromarray(_texture(np.asarray(image), label, rng))
    gain = rng.uniform(0.7, 1.25) * (1.0 + rng.normal(0.0, 0.05, 3))
    ramp = (np.arange(256) / 255.0) ** rng.uniform(0.8, 1.25)
    image = image.point(
        np.clip(255.0 * ramp * gain[:, None], 0, 255).astype(np.uint8).ravel().tolist()
    )
    sharp = rng.random() < 0.85
    radius = h / 256 * (rng.uniform(0.4, 0.8) if sharp else rng.uniform(1.2, 1.8))
    return np.array(image.filter(ImageFilter.BoxBlur(radius)))
