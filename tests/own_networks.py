"""Networks a user might name as ``model.net`` (tests only): each breaks one of train.py's
requirements, or meets one a different way."""

import torch
from torch import nn


class QuarterLogits(nn.Module):
    """Logits at a quarter of the input size (as many networks return them)."""

    def __init__(self, num_classes: int) -> None:
        super().__init__()
        self.conv = nn.Conv2d(3, num_classes, 4, stride=4)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.conv(x)


class DictLogits(QuarterLogits):
    """Logits under the key ``out`` of a dict, as torchvision's segmentation models return."""

    def forward(self, x: torch.Tensor) -> dict[str, torch.Tensor]:
        return {"out": self.conv(x)}


class ThreeClasses(QuarterLogits):
    """Ignores ``num_classes``: always 3 output channels."""

    def __init__(self, num_classes: int) -> None:
        super().__init__(3)


class NoClasses(nn.Module):
    """Takes no ``num_classes``."""

    def __init__(self, width: int = 4) -> None:
        super().__init__()
        self.conv = nn.Conv2d(3, width, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.conv(x)
