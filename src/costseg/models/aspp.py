"""Atrous spatial pyramid pooling (DeepLabv3), written without torchvision.

Same modules, state-dict keys, random draws and outputs as torchvision's
``torchvision.models.segmentation.deeplabv3.ASPP``, whose import would pull in ``torch._dynamo``.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import nn
from torch.nn import functional as F

__all__ = ["ASPP"]


def _branch(in_channels: int, out_channels: int, dilation: int | None = None) -> nn.Sequential:
    """Conv-BN-ReLU: 1x1 without ``dilation``, else 3x3 with that dilation."""
    if dilation is None:
        conv = nn.Conv2d(in_channels, out_channels, 1, bias=False)
    else:
        conv = nn.Conv2d(
            in_channels, out_channels, 3, padding=dilation, dilation=dilation, bias=False
        )
    return nn.Sequential(conv, nn.BatchNorm2d(out_channels), nn.ReLU())


class _ImagePooling(nn.Sequential):
    """Global average pooling, 1x1 conv-BN-ReLU, then bilinear upsampling to the input size."""

    def __init__(self, in_channels: int, out_channels: int) -> None:
        super().__init__(nn.AdaptiveAvgPool2d(1), *_branch(in_channels, out_channels))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = super().forward(x)
        return F.interpolate(y, size=x.shape[-2:], mode="bilinear", align_corners=False)


class ASPP(nn.Module):
    """A 1x1 branch, one dilated 3x3 branch per rate and image pooling, concatenated and projected.

    Args:
        in_channels: channels of the input features.
        atrous_rates: dilations of the 3x3 branches, e.g. (6, 12, 18) at output stride 16.
        out_channels: channels of every branch and of the output.

    Example:
        >>> aspp = ASPP(16, (6, 12, 18), 8)
        >>> aspp(torch.rand(2, 16, 5, 7)).shape
        torch.Size([2, 8, 5, 7])
    """

    def __init__(
        self, in_channels: int, atrous_rates: Sequence[int], out_channels: int = 256
    ) -> None:
        super().__init__()
        self.convs = nn.ModuleList(
            [
                _branch(in_channels, out_channels),
                *(_branch(in_channels, out_channels, rate) for rate in atrous_rates),
                _ImagePooling(in_channels, out_channels),
            ]
        )
        self.project = nn.Sequential(
            *_branch(len(self.convs) * out_channels, out_channels), nn.Dropout(0.5)
        )

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """(B, in_channels, h, w) → (B, out_channels, h, w)."""
        return self.project(torch.cat([conv(x) for conv in self.convs], dim=1))
