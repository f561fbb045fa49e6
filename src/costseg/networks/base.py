"""What every network source shares: the uint8-image wrapper and the check of loaded weights."""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor, nn
from torch.nn import functional as F

__all__ = [
    "IMAGENET_MEAN",
    "IMAGENET_STD",
    "ImageNetwork",
    "at_input_size",
    "check_state_keys",
    "normalised",
    "resize_bilinear",
]

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)


def normalised(
    images: Tensor, mean: Tensor, std: Tensor, divisor: float = 255.0, channels_last: bool = False
) -> Tensor:
    """(B, 3, H, W) uint8 images as a network's float input: ``(x / divisor − mean) / std``
    (mean, std: (1, 3, 1, 1)), channels-last if asked. Dividing by 255 (not multiplying by
    1/255) is what costseg trains on, bit for bit."""
    x = (images.float() / divisor - mean) / std
    return x.contiguous(memory_format=torch.channels_last) if channels_last else x


def at_input_size(logits: Tensor, images: Tensor) -> Tensor:
    """(B, N, h, w) logits resized bilinearly to the (H, W) of ``images`` (unchanged at it).

    >>> at_input_size(torch.zeros(1, 19, 8, 16), torch.zeros(1, 3, 32, 64)).shape
    torch.Size([1, 19, 32, 64])
    """
    if logits.shape[-2:] == images.shape[-2:]:
        return logits
    return resize_bilinear(logits, tuple(images.shape[-2:]))


def resize_bilinear(maps: Tensor, size: tuple[int, int]) -> Tensor:
    """(B, C, h, w) float maps resized bilinearly to ``size`` (H, W), half-pixel centres (as
    torchvision's and the official Cityscapes evaluators' resizing)."""
    return F.interpolate(maps, size=size, mode="bilinear", align_corners=False)


class ImageNetwork(nn.Module):
    """A network behind its input normalisation, with logits resized to the input size.

    Args:
        net: maps (B, 3, H, W) normalised images to (B, N, h, w) logits (or a dict holding them
            under ``"out"``, as torchvision's segmentation models return).
        mean, std: per-channel normalisation, applied after the rescaling.
        rescale: factor taking uint8 values to the network's range (1/255: [0, 1]).
        channels_last: run the network on channels-last tensors (as costseg trains).

    Example:
        >>> net = ImageNetwork(nn.Conv2d(3, 19, 4, stride=4))
        >>> net(torch.zeros(2, 3, 32, 48, dtype=torch.uint8)).shape
        torch.Size([2, 19, 32, 48])
    """

    def __init__(
        self,
        net: nn.Module,
        mean: tuple[float, ...] = IMAGENET_MEAN,
        std: tuple[float, ...] = IMAGENET_STD,
        rescale: float = 1 / 255,
        channels_last: bool = False,
    ) -> None:
        super().__init__()
        # costseg trains channels-last; the same layout gives the same convolution kernels.
        self.net = net.to(memory_format=torch.channels_last) if channels_last else net
        self.register_buffer("mean", torch.tensor(mean).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("std", torch.tensor(std).view(1, 3, 1, 1), persistent=False)
        self.divisor = 1.0 / rescale  # 1 / (1/255) rounds back to exactly 255 in float32
        self.channels_last = channels_last
        self.eval()

    def forward(self, images: Tensor) -> Tensor:
        """(B, 3, H, W) uint8 RGB → (B, N, H, W) float logits."""
        if images.dtype != torch.uint8 or images.ndim != 4 or images.shape[1] != 3:
            raise ValueError(
                "expected (B, 3, H, W) uint8 RGB images; "
                f"got {tuple(images.shape)} {str(images.dtype).removeprefix('torch.')}"
            )
        logits = self.net(normalised(images, self.mean, self.std, self.divisor, self.channels_last))
        if isinstance(logits, dict):  # torchvision's segmentation models: {"out": ..., "aux": ...}
            logits = logits["out"]
        return at_input_size(logits, images)


def check_state_keys(expected: dict[str, Tensor], state: dict[str, Any], what: str) -> None:
    """ValueError naming the first missing / unexpected keys, then the first wrong shape."""
    missing = [k for k in expected if k not in state and not k.endswith("num_batches_tracked")]
    unexpected = [k for k in state if k not in expected]
    if missing or unexpected:
        raise ValueError(
            f"{what}: {len(missing)} missing keys (first: {', '.join(missing[:3]) or '-'}), "
            f"{len(unexpected)} unexpected keys (first: {', '.join(unexpected[:3]) or '-'})"
        )
    for key, value in expected.items():
        got = getattr(state.get(key, value), "shape", None)
        if got != value.shape:
            raise ValueError(
                f"{what}: {key} has shape {tuple(got or ())}, expected {tuple(value.shape)}"
            )
