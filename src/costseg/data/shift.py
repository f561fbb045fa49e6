"""Shifted test sets (docs/definitions.md §17): the same scenes and labels seen through a
corruption at severity 1–5 (0 = the image itself), deterministic for a seed and an image.

Weather, lens, blur, Gaussian noise and JPEG are albumentations' transforms, with the ImageNet-C
severity tables (Hendrycks & Dietterich 2019) where albumentations has the same parameters
(Gaussian noise, defocus, JPEG, spatter). Shot noise, brightness and contrast follow
ImageNet-C's formulas, which albumentations' transforms do not (``ShotNoise`` adds the noise in
linear light, ``RandomBrightnessContrast`` scales contrast around 0, not the mean); darkness
(night) is written here (ImageNet-C has none). Spatial parameters are in pixels,
as ImageNet-C and Cityscapes-C use them, not scaled with the image.

>>> image = np.full((4, 6, 3), 100, np.uint8)
>>> shift_image(image, Shift("contrast", 0), seed=0) is image
True
>>> int(shift_image(image, Shift("brightness", 5), seed=0)[0, 0, 0])   # V: 100/255 + 0.5
227
"""

from __future__ import annotations

import importlib
import zlib
from collections.abc import Callable
from dataclasses import dataclass
from functools import cache
from typing import TYPE_CHECKING, Any

import numpy as np
import torch
from torch.utils.data import Dataset

if TYPE_CHECKING:
    import albumentations


class _OnFirstUse:
    """albumentations, imported when a transform is first built: its import takes seconds, and
    naming a shift (``parse_shift``, an option check) needs none of it."""

    def __getattr__(self, name: str) -> Any:
        return getattr(importlib.import_module("albumentations"), name)


A = _OnFirstUse()

__all__ = [
    "BY_ALBUMENTATIONS",
    "CORRUPTIONS",
    "SEVERITIES",
    "WRITTEN_HERE",
    "Shift",
    "ShiftedDataset",
    "parse_shift",
    "shift_image",
]

SEVERITIES = range(0, 6)


def _night(image: np.ndarray, severity: int, rng: np.random.Generator) -> np.ndarray:
    """Darkness: ``poisson(c · b · x^γ) / c`` on x in [0, 1], a dimmer, more contrasted scene
    seen with the shot noise of fewer photons."""
    b, gamma, photons = ((0.6, 1.2, 120), (0.45, 1.4, 90), (0.3, 1.6, 60),
                         (0.2, 1.8, 45), (0.12, 2.0, 30))[severity - 1]  # fmt: skip
    dim = b * (image / 255.0) ** gamma
    return rng.poisson(dim * photons) / photons * 255


def _shot_noise(image: np.ndarray, severity: int, rng: np.random.Generator) -> np.ndarray:
    """ImageNet-C: ``poisson(x · c) / c`` on x in [0, 1] with c photons per unit intensity
    (albumentations' ShotNoise has another variance: it adds the noise in linear light)."""
    photons = (60, 25, 12, 5, 3)[severity - 1]
    return rng.poisson(image / 255.0 * photons) / photons * 255


def _brightness(image: np.ndarray, severity: int, rng: np.random.Generator) -> np.ndarray:
    """ImageNet-C: the HSV value V = max(R, G, B) raised by c and clipped at 1, hue and
    saturation kept: every channel scales by min(V + c, 1) / V (black becomes grey c)."""
    c = (0.1, 0.2, 0.3, 0.4, 0.5)[severity - 1]
    x = image / 255.0
    v = x.max(-1, keepdims=True)
    scaled = x * (np.minimum(v + c, 1.0) / np.where(v > 0, v, 1.0))
    return np.where(v > 0, scaled, c) * 255


def _contrast(image: np.ndarray, severity: int, rng: np.random.Generator) -> np.ndarray:
    """ImageNet-C: each channel pulled towards its mean, ``(x - mean) · c + mean``."""
    c = (0.4, 0.3, 0.2, 0.1, 0.05)[severity - 1]
    x = image.astype(np.float64)
    mean = x.mean((0, 1), keepdims=True)
    return (x - mean) * c + mean


# Each albumentations corruption: severity 1–5 → its transform (p = 1: always applied).
def _fog(s: int) -> albumentations.BasicTransform:
    f = (0.2, 0.35, 0.5, 0.65, 0.8)[s - 1]
    return A.RandomFog(fog_coef_range=(f, f), alpha_coef=0.1, p=1)


def _rain(s: int) -> albumentations.BasicTransform:
    kind, brightness, blur = (("drizzle", 0.9, 3), ("default", 0.8, 3), ("heavy", 0.75, 5),
                              ("heavy", 0.65, 7), ("torrential", 0.55, 7))[s - 1]  # fmt: skip
    return A.RandomRain(rain_type=kind, brightness_coefficient=brightness, blur_value=blur, p=1)


def _snow(s: int) -> albumentations.BasicTransform:
    v = (0.1, 0.2, 0.3, 0.4, 0.5)[s - 1]
    return A.RandomSnow(snow_point_range=(v, v), method="bleach", p=1)


def _spatter(s: int) -> albumentations.BasicTransform:
    """ImageNet-C's table: (mean, std, gauss_sigma, cutout_threshold, intensity, mode), the mud
    intensity 1.5 lowered to albumentations' largest, 1."""
    mean, std, sigma, threshold, intensity, mode = (
        (0.65, 0.3, 4, 0.69, 0.6, "rain"), (0.65, 0.3, 3, 0.68, 0.6, "rain"),
        (0.65, 0.3, 2, 0.68, 0.5, "rain"), (0.65, 0.3, 1, 0.65, 1.0, "mud"),
        (0.67, 0.4, 1, 0.65, 1.0, "mud"),
    )[s - 1]  # fmt: skip
    return A.Spatter(mean=mean, std=std, gauss_sigma=sigma, cutout_threshold=threshold,
                     intensity=intensity, mode=mode, p=1)  # fmt: skip


def _motion_blur(s: int) -> albumentations.BasicTransform:
    """A kernel of 2σ + 1 pixels for ImageNet-C's σ (3, 5, 8, 12, 15), in a random direction."""
    k = (7, 11, 17, 25, 31)[s - 1]
    return A.MotionBlur(blur_limit=(k, k), allow_shifted=False, p=1)


def _defocus_blur(s: int) -> albumentations.BasicTransform:
    radius, alias = ((3, 0.1), (4, 0.5), (6, 0.5), (8, 0.5), (10, 0.5))[s - 1]
    return A.Defocus(radius=(radius, radius), alias_blur=(alias, alias), p=1)


def _gaussian_noise(s: int) -> albumentations.BasicTransform:
    std = (0.08, 0.12, 0.18, 0.26, 0.38)[s - 1]
    return A.GaussNoise(std_range=(std, std), p=1)


def _jpeg(s: int) -> albumentations.BasicTransform:
    quality = (25, 18, 15, 10, 7)[s - 1]
    return A.ImageCompression(quality_range=(quality, quality), p=1)


# name → the albumentations transform of a severity
BY_ALBUMENTATIONS: dict[str, Callable[[int], albumentations.BasicTransform]] = {
    "fog": _fog,
    "rain": _rain,
    "snow": _snow,
    "spatter": _spatter,
    "motion_blur": _motion_blur,
    "defocus_blur": _defocus_blur,
    "gaussian_noise": _gaussian_noise,
    "jpeg": _jpeg,
}
# name → (image, severity, rng) → image, written here
WRITTEN_HERE: dict[str, Callable[[np.ndarray, int, np.random.Generator], np.ndarray]] = {
    "night": _night,
    "shot_noise": _shot_noise,
    "brightness": _brightness,
    "contrast": _contrast,
}
CORRUPTIONS = (*BY_ALBUMENTATIONS, *WRITTEN_HERE)


@dataclass(frozen=True)
class Shift:
    """A corruption (a name of :data:`CORRUPTIONS`) at a severity 0–5."""

    name: str
    severity: int

    def __str__(self) -> str:
        return f"{self.name}:{self.severity}"


def parse_shift(text: str) -> Shift:
    """``fog:3`` → Shift("fog", 3); ValueError naming what is wrong.

    >>> parse_shift("night:2")
    Shift(name='night', severity=2)
    """
    name, _, severity = text.partition(":")
    if name not in CORRUPTIONS:
        raise ValueError(f"unknown shift {name!r}: expected one of {', '.join(CORRUPTIONS)}")
    if not severity.isdigit() or int(severity) not in SEVERITIES:
        raise ValueError(f"--shift {text}: expected NAME:SEVERITY with a severity 0 to 5")
    return Shift(name, int(severity))


@cache
def _transform(name: str, severity: int) -> albumentations.Compose:
    return A.Compose([BY_ALBUMENTATIONS[name](severity)])


def image_seed(seed: int, shift: Shift, index: int) -> int:
    """The seed of one image's corruption: the same for a (seed, shift, image) in any order."""
    key = [seed, zlib.crc32(shift.name.encode()), shift.severity, index]
    return int(np.random.SeedSequence(key).generate_state(1)[0])


def shift_image(image: np.ndarray, shift: Shift, seed: int) -> np.ndarray:
    """(H, W, 3) uint8 RGB seen through ``shift`` (deterministic for ``seed``); severity 0 returns
    ``image`` itself."""
    if shift.severity == 0:
        return image
    if shift.name in WRITTEN_HERE:
        out = WRITTEN_HERE[shift.name](image, shift.severity, np.random.default_rng(seed))
    else:
        transform = _transform(shift.name, shift.severity)
        transform.set_random_seed(seed)
        out = transform(image=np.ascontiguousarray(image))["image"]
    return np.clip(np.rint(out), 0, 255).astype(np.uint8) if out.dtype != np.uint8 else out


class ShiftedDataset(Dataset):
    """``dataset`` (items ``(image (3, H, W) uint8, label, ...)``) with every image seen through
    ``shift`` from index ``onset`` on (those before it as they are: a stream whose conditions
    change); labels, instance ids (``with_instances``), anomaly masks (``with_anomalies``) and
    every other attribute those of ``dataset``."""

    def __init__(self, dataset: Dataset, shift: Shift, seed: int = 0, onset: int = 0) -> None:
        self.dataset, self.shift, self.seed, self.onset = dataset, shift, seed, onset

    def __len__(self) -> int:
        return len(self.dataset)  # type: ignore[arg-type]

    def __getattr__(self, name: str):
        if name == "dataset":  # not yet set (unpickling)
            raise AttributeError(name)
        return getattr(self.dataset, name)

    def __getitem__(self, index: int):
        return self._shifted(index, self.dataset[index])

    def with_instances(self, index: int):
        return self._shifted(index, self.dataset.with_instances(index))

    def with_anomalies(self, index: int):
        return self._shifted(index, self.dataset.with_anomalies(index))

    def _shifted(self, index: int, item: tuple) -> tuple:
        if index < self.onset:
            return item
        image, *rest = item
        array = image.permute(1, 2, 0).numpy()
        shifted = shift_image(array, self.shift, image_seed(self.seed, self.shift, index))
        return (
            torch.from_numpy(np.ascontiguousarray(shifted)).permute(2, 0, 1).contiguous(),
            *rest,
        )
