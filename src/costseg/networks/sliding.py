"""Sliding-window inference (``docs/definitions.md §13``), mmsegmentation's ``slide`` convention.

Windows of ``crop`` (h, w) start every ``stride`` (h, w): ``ceil((H - h) / s_h) + 1`` rows and
likewise columns, the last clamped so that it ends on the image's border. Along a side shorter
than the crop the window is the whole side (the network runs on the image's own extent there:
nothing is padded), so a crop at least as large as the image is exactly the whole-image forward.
Each pixel's logits are the mean over the windows that cover it.

>>> window_starts(10, 4, 3), window_starts(11, 4, 3), window_starts(3, 4, 2)
([0, 3, 6], [0, 3, 6, 7], [0])
>>> net = SlidingWindow(torch.nn.Conv2d(3, 2, 1), crop=(4, 4), stride=(2, 3))
>>> net(torch.rand(1, 3, 6, 9)).shape
torch.Size([1, 2, 6, 9])
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

DEFAULT_CROPS_PER_FORWARD = 8


def window_starts(size: int, crop: int, stride: int) -> list[int]:
    """Where the windows along one side of ``size`` pixels start (each ``min(crop, size)`` long).

    Args:
        size: the image's height or width.
        crop: the window's length along that side.
        stride: the step between window starts (<= ``crop``, so every pixel is covered).
    """
    count = max(size - crop + stride - 1, 0) // stride + 1
    return [max(min(i * stride + crop, size) - crop, 0) for i in range(count)]


class SlidingWindow(nn.Module):
    """A network whose logits are the per-pixel mean over sliding windows.

    Args:
        network: (B, 3, h, w) uint8 images → (B, N, h, w) logits (an
            :class:`~costseg.networks.base.ImageNetwork`).
        crop: the windows' (height, width).
        stride: the steps (height, width) between windows, each <= the crop's.
        crops_per_forward: windows of all images of a batch go through the network in chunks of
            at most this many crops (at least one window per chunk), so memory stays that of a
            few crops, not of all windows at once.

    Raises:
        ValueError: a size that is not positive, or a stride larger than the crop.
    """

    def __init__(
        self,
        network: nn.Module,
        crop: tuple[int, int],
        stride: tuple[int, int],
        crops_per_forward: int = DEFAULT_CROPS_PER_FORWARD,
    ) -> None:
        super().__init__()
        if min(*crop, *stride) < 1 or stride[0] > crop[0] or stride[1] > crop[1]:
            raise ValueError(f"windows need 1 <= stride <= crop; got crop {crop}, stride {stride}")
        self.network, self.crop, self.stride = network, tuple(crop), tuple(stride)
        self.crops_per_forward = crops_per_forward

    def forward(self, images: Tensor) -> Tensor:
        """(B, 3, H, W) uint8 images → (B, N, H, W) float logits, averaged over windows."""
        size = tuple(images.shape[-2:])
        rows, cols = (
            window_starts(n, c, s) for n, c, s in zip(size, self.crop, self.stride, strict=True)
        )
        if len(rows) == len(cols) == 1:  # one window: the whole image
            return self.network(images)
        h, w = min(self.crop[0], size[0]), min(self.crop[1], size[1])
        boxes = [(y, x) for y in rows for x in cols]
        n = len(images)
        total, count = None, images.new_zeros((1, 1, *size), dtype=torch.float32)
        per_forward = max(1, self.crops_per_forward // n)
        for first in range(0, len(boxes), per_forward):
            chunk = boxes[first : first + per_forward]
            crops = torch.cat([images[:, :, y : y + h, x : x + w] for y, x in chunk])
            logits = self.network(crops).float()
            if total is None:
                total = logits.new_zeros((n, logits.shape[1], *size))
            for k, (y, x) in enumerate(chunk):
                total[:, :, y : y + h, x : x + w] += logits[k * n : (k + 1) * n]
                count[:, :, y : y + h, x : x + w] += 1
        return total / count

    def describe(self) -> str:
        """The windows, for every output: ``slide crop 64x64 stride 48x48``."""
        return f"slide crop {self.crop[0]}x{self.crop[1]} stride {self.stride[0]}x{self.stride[1]}"
