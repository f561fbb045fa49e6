"""ResNet-18/34/50/101 trunks for DeepLabv3+, written without torchvision.

Importing torchvision imports ``torch._dynamo`` (through ``torchvision.ops``), about 2 s of
``evaluate.py``'s start-up; these trunks avoid it. Module names, and so the state-dict keys, are
those of torchvision's ``resnet*`` minus ``avgpool`` / ``fc``: torchvision state dicts load as they
are, and so do checkpoints of the torchvision-built model. Construction consumes the random
generator as torchvision's does, so a seeded build gives the same weights.

Dilation follows what ``costseg.models.deeplabv3plus`` did with torchvision: stage 4 (and stage 3
at output stride 8) trades its stride 2 for dilation 2 (4 for stage 4 at stride 8).

* Bottleneck (ResNet-50/101, stride on the 3x3 conv, "v1.5"): torchvision's
  ``replace_stride_with_dilation``: a dilated stage's first block keeps the previous dilation.
* BasicBlock (ResNet-18/34), which torchvision cannot dilate: every 3x3 conv of a dilated stage
  gets the stage's dilation (segmentation_models_pytorch's convention).
"""

from __future__ import annotations

import torch
from torch import nn

__all__ = ["RESNETS", "BasicBlock", "Bottleneck", "ResNetTrunk"]


def _conv3x3(in_channels: int, out_channels: int, stride: int = 1, dilation: int = 1) -> nn.Conv2d:
    return nn.Conv2d(
        in_channels, out_channels, 3, stride, padding=dilation, dilation=dilation, bias=False
    )


class BasicBlock(nn.Module):
    """Two 3x3 conv-BN (both with ``dilation``) plus the identity or ``downsample`` shortcut."""

    expansion = 1

    def __init__(
        self,
        in_channels: int,
        planes: int,
        stride: int = 1,
        downsample: nn.Module | None = None,
        dilation: int = 1,
    ) -> None:
        super().__init__()
        self.conv1 = _conv3x3(in_channels, planes, stride, dilation)
        self.bn1 = nn.BatchNorm2d(planes)
        self.relu = nn.ReLU(inplace=True)
        self.conv2 = _conv3x3(planes, planes, 1, dilation)
        self.bn2 = nn.BatchNorm2d(planes)
        self.downsample = downsample

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        out = self.relu(self.bn1(self.conv1(x)))
        out = self.bn2(self.conv2(out))
        out += x if self.downsample is None else self.downsample(x)
        return self.relu(out)


class Bottleneck(nn.Module):
    """1x1 reduce, 3x3 (``stride``, ``dilation``), 1x1 expand by 4, plus the shortcut."""

    expansion = 4

    def __init__(
        self,
        in_channels: int,
        planes: int,
        stride: int = 1,
        downsample: nn.Module | None = None,
        dilation: int = 1,
    ) -> None:
        super().__init__()
        self.conv1 = nn.Conv2d(in_channels, planes, 1, bias=False)
        self.bn1 = nn.BatchNorm2d(planes)
        self.conv2 = _conv3x3(planes, planes, stride, dilation)
        self.bn2 = nn.BatchNorm2d(planes)
        self.conv3 = nn.Conv2d(planes, planes * self.expansion, 1, bias=False)
        self.bn3 = nn.BatchNorm2d(planes * self.expansion)
        self.relu = nn.ReLU(inplace=True)
        self.downsample = downsample

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        out = self.relu(self.bn1(self.conv1(x)))
        out = self.relu(self.bn2(self.conv2(out)))
        out = self.bn3(self.conv3(out))
        out += x if self.downsample is None else self.downsample(x)
        return self.relu(out)


RESNETS: dict[str, tuple[type[BasicBlock | Bottleneck], tuple[int, int, int, int]]] = {
    "resnet18": (BasicBlock, (2, 2, 2, 2)),
    "resnet34": (BasicBlock, (3, 4, 6, 3)),
    "resnet50": (Bottleneck, (3, 4, 6, 3)),
    "resnet101": (Bottleneck, (3, 4, 23, 3)),
}
"""Name → (block, blocks per stage), as in torchvision."""


class ResNetTrunk(nn.Module):
    """A ResNet without its classifier, giving the stride-4 and the last stage's features.

    Args:
        name: one of `RESNETS`.
        output_stride: 32 (no dilation), 16 or 8, the stride of the ``"out"`` features.
        width: channels of the stem and the first stage, doubled by each later stage (64 in
            torchvision's ResNets; 32 gives a network about 4x cheaper).

    Raises:
        ValueError: unknown ``name`` or unsupported ``output_stride``.

    Example:
        >>> trunk = ResNetTrunk("resnet18", output_stride=8)
        >>> {k: tuple(v.shape) for k, v in trunk(torch.rand(1, 3, 64, 96)).items()}
        {'low': (1, 64, 16, 24), 'out': (1, 512, 8, 12)}
        >>> trunk = ResNetTrunk("resnet18", output_stride=32, width=32)
        >>> {k: tuple(v.shape) for k, v in trunk(torch.rand(1, 3, 64, 96)).items()}
        {'low': (1, 32, 16, 24), 'out': (1, 256, 2, 3)}
    """

    def __init__(self, name: str, output_stride: int = 16, width: int = 64) -> None:
        if name not in RESNETS:
            raise ValueError(f"name must be one of {', '.join(RESNETS)}; got {name!r}")
        if output_stride not in (8, 16, 32):
            raise ValueError(f"output_stride must be 8, 16 or 32; got {output_stride!r}")
        super().__init__()
        block, depths = RESNETS[name]
        self.conv1 = nn.Conv2d(3, width, 7, stride=2, padding=3, bias=False)
        self.bn1 = nn.BatchNorm2d(width)
        self.relu = nn.ReLU(inplace=True)
        self.maxpool = nn.MaxPool2d(kernel_size=3, stride=2, padding=1)
        in_channels, dilation = width, 1
        dilate = (False, False, output_stride == 8, output_stride <= 16)
        for i, (planes, blocks) in enumerate(
            zip((width, 2 * width, 4 * width, 8 * width), depths, strict=True)
        ):
            stride, previous = (2 if i else 1), dilation
            if dilate[i]:
                dilation, stride = dilation * stride, 1
            first = previous if block is Bottleneck else dilation
            stage = _stage(block, in_channels, planes, blocks, stride, first, dilation)
            self.add_module(f"layer{i + 1}", stage)
            in_channels = planes * block.expansion
        # torchvision builds its 1000-class fc here: draw what it draws, so seeded weights agree.
        torch.empty(1000, in_channels).uniform_()
        torch.empty(1000).uniform_()
        for m in self.modules():
            if isinstance(m, nn.Conv2d):
                nn.init.kaiming_normal_(m.weight, mode="fan_out", nonlinearity="relu")
            elif isinstance(m, nn.BatchNorm2d):
                nn.init.ones_(m.weight)
                nn.init.zeros_(m.bias)

    def forward(self, x: torch.Tensor) -> dict[str, torch.Tensor]:
        """(B, 3, H, W) → {"low": stride-4 ``layer1`` output, "out": ``layer4`` output}."""
        low = self.layer1(self.maxpool(self.relu(self.bn1(self.conv1(x)))))
        return {"low": low, "out": self.layer4(self.layer3(self.layer2(low)))}


def _stage(
    block: type[BasicBlock | Bottleneck],
    in_channels: int,
    planes: int,
    blocks: int,
    stride: int,
    first_dilation: int,
    dilation: int,
) -> nn.Sequential:
    downsample = None
    out_channels = planes * block.expansion
    if stride != 1 or in_channels != out_channels:  # built before the block, as in torchvision
        downsample = nn.Sequential(
            nn.Conv2d(in_channels, out_channels, 1, stride, bias=False),
            nn.BatchNorm2d(out_channels),
        )
    return nn.Sequential(
        block(in_channels, planes, stride, downsample, first_dilation),
        *(block(out_channels, planes, dilation=dilation) for _ in range(blocks - 1)),
    )
