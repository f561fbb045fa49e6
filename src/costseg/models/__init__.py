"""Segmentation networks: plain ``nn.Module``s that know nothing of Lightning or costs."""

from costseg.models.deeplabv3plus import (
    BACKBONES,
    DeepLabV3Plus,
    DeepLabV3PlusDecoder,
    load_backbone_weights,
)

__all__ = ["BACKBONES", "DeepLabV3Plus", "DeepLabV3PlusDecoder", "load_backbone_weights"]
