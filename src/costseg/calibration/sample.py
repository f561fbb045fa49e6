"""A uniform sample of labelled pixels per image, to fit a scaling in constant memory
(docs/definitions.md §6)."""

from __future__ import annotations

import torch
from torch import Tensor

from costseg.calibration.scaling import Scaling, ScalingKind, fit_temperature, fit_vector_scaling
from costseg.classes import IGNORE_INDEX


class PixelSampler:
    """A seeded uniform sample of labelled pixels per image, to fit a scaling in constant memory.

    Sampling: for each image of each batch, among its pixels whose target is not
    ``ignore_index``, ``pixels_per_image`` are drawn uniformly without replacement (all of them
    when there are fewer), with ``torch.randperm`` from one CPU generator seeded with ``seed``
    and advanced image after image; so the same images in the same order give the same sample,
    whatever the batching. Logits are kept as float32 on the CPU: memory grows with the number of
    images times ``pixels_per_image``, never with the resolution.

    Args:
        pixels_per_image: Pixels kept per image at most (>= 1).
        ignore_index: Label of pixels never sampled.
        seed: Seed of the sampling generator.

    >>> sampler = PixelSampler(pixels_per_image=3)
    >>> sampler.update(torch.randn(2, 4, 5, 5), torch.randint(0, 4, (2, 5, 5)))
    >>> sampler.num_images, sampler.num_pixels, sampler.fit("temperature").kind
    (2, 6, 'temperature')
    """

    def __init__(
        self, pixels_per_image: int = 4096, ignore_index: int = IGNORE_INDEX, seed: int = 0
    ) -> None:
        if not isinstance(pixels_per_image, int) or pixels_per_image < 1:
            raise ValueError(f"pixels_per_image must be an integer >= 1; got {pixels_per_image!r}")
        self.pixels_per_image, self.ignore_index = pixels_per_image, ignore_index
        self._generator = torch.Generator().manual_seed(seed)
        self._logits: list[Tensor] = []
        self._target: list[Tensor] = []
        self.num_images = 0

    def update(self, logits: Tensor, target: Tensor) -> None:
        """Sample a batch: logits (B, N, H, W) float, target (B, H, W) integer."""
        if logits.ndim != 4 or target.ndim != 3 or logits.shape[0] != target.shape[0]:
            raise ValueError(
                "expected logits (B, N, H, W) and target (B, H, W); got "
                f"{tuple(logits.shape)} and {tuple(target.shape)}"
            )
        if self._logits and logits.shape[1] != self._logits[0].shape[1]:
            raise ValueError(
                f"expected {self._logits[0].shape[1]} classes as before; got {logits.shape[1]}"
            )
        for image, label in zip(logits, target, strict=True):
            where = (label.reshape(-1) != self.ignore_index).nonzero()[:, 0]
            if len(where) > self.pixels_per_image:
                pick = torch.randperm(len(where), generator=self._generator)
                where = where[pick[: self.pixels_per_image].to(where.device)]
            self._logits.append(image.reshape(image.shape[0], -1)[:, where].T.float().cpu())
            self._target.append(label.reshape(-1)[where].long().cpu())
            self.num_images += 1

    @property
    def num_pixels(self) -> int:
        """Pixels in the sample."""
        return sum(len(t) for t in self._target)

    def tensors(self) -> tuple[Tensor, Tensor]:
        """The sample: (P, N) float32 logits and (P,) int64 labels (no ignored pixel)."""
        if not self._target:
            raise ValueError("the sampler is empty: call update() with at least one batch")
        return torch.cat(self._logits), torch.cat(self._target)

    def fit(self, kind: ScalingKind = "temperature") -> Scaling:
        """Fit a scaling on the sample; ``fitted_on`` says how many images and pixels."""
        if kind == "none":
            return Scaling()
        logits, target = self.tensors()
        source = (
            f"{self.num_images} images, {self.num_pixels} pixels "
            f"(at most {self.pixels_per_image} per image, uniform)"
        )
        if kind == "temperature":
            return Scaling("temperature", fit_temperature(logits, target), fitted_on=source)
        if kind == "vector":
            a, b = fit_vector_scaling(logits, target)
            return Scaling("vector", scale=a.tolist(), offset=b.tolist(), fitted_on=source)
        raise ValueError(f"kind must be 'none', 'temperature' or 'vector'; got {kind!r}")
