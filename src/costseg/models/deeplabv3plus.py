"""DeepLabv3+ (Chen et al., ECCV 2018) as a plain ``nn.Module`` on a ResNet or MobileNetV3 trunk.

The backbone gives stride-4 low-level features and stride-16 (or 8) high-level features;
ASPP runs on the high-level features, and the decoder merges its output with the low-level
features before the classifier. Logits are resized bilinearly to the input size.
The module knows nothing of Lightning, costs or datasets.

The ResNet trunks (`costseg.models.resnet`) and the ASPP (`costseg.models.aspp`) are costseg's
own, with torchvision's module names and outputs, so that importing this module does not import
torchvision (and ``torch._dynamo`` with it, about 2 s); only ``mobilenet_v3_large`` builds
torchvision's network, importing torchvision when it is built.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import torch
from torch import nn
from torch.nn import functional as F

from costseg.checkpoints import read_torch_file
from costseg.models.aspp import ASPP
from costseg.models.resnet import ResNetTrunk

__all__ = ["BACKBONES", "DeepLabV3Plus", "DeepLabV3PlusDecoder", "load_backbone_weights"]

# DeepLabv3+'s rates at output stride 16 and 8; at 32 (no dilated stage) half of 16's.
ATROUS_RATES: dict[int, tuple[int, int, int]] = {32: (3, 6, 9), 16: (6, 12, 18), 8: (12, 24, 36)}
LOW_LEVEL_CHANNELS = 48  # the paper's projection width for the stride-4 features
_HEAD_PREFIXES = ("fc.", "classifier.")  # classification heads that the backbone drops


@dataclass(frozen=True)
class _BackboneSpec:
    """How to build one backbone (output stride → module giving {"low", "out"} features)."""

    build: Callable[[int], nn.Module]
    low_channels: int
    high_channels: int
    output_strides: tuple[int, ...]


def _resnet(name: str, width: int = 64) -> Callable[[int], nn.Module]:
    return lambda output_stride: ResNetTrunk(name, output_stride, width)


def _mobilenet_v3_large(output_stride: int) -> nn.Module:
    # torchvision (which imports torch._dynamo, about 2 s) is imported for this backbone only.
    from torchvision.models import mobilenet_v3_large
    from torchvision.models.feature_extraction import create_feature_extractor

    # `dilated=True` replaces the last stride-2 stage by dilation 2, giving output stride 16.
    # features.3 is the last stride-4 block; features.16 the final 960-channel conv.
    net = mobilenet_v3_large(weights=None, dilated=True)
    return create_feature_extractor(net, {"features.3": "low", "features.16": "out"})


_SPECS: dict[str, _BackboneSpec] = {
    "resnet18": _BackboneSpec(_resnet("resnet18"), 64, 512, (8, 16, 32)),
    # ResNet-18 at half width (base 32): a training step about 2.4x cheaper on a CPU (the demo)
    "resnet18_w32": _BackboneSpec(_resnet("resnet18", 32), 32, 256, (8, 16, 32)),
    "resnet34": _BackboneSpec(_resnet("resnet34"), 64, 512, (8, 16, 32)),
    "resnet50": _BackboneSpec(_resnet("resnet50"), 256, 2048, (8, 16, 32)),
    "resnet101": _BackboneSpec(_resnet("resnet101"), 256, 2048, (8, 16, 32)),
    "mobilenet_v3_large": _BackboneSpec(_mobilenet_v3_large, 24, 960, (16,)),
}
BACKBONES: tuple[str, ...] = tuple(_SPECS)


def _conv_bn_relu(in_channels: int, out_channels: int, kernel_size: int) -> nn.Sequential:
    return nn.Sequential(
        nn.Conv2d(in_channels, out_channels, kernel_size, padding=kernel_size // 2, bias=False),
        nn.BatchNorm2d(out_channels),
        nn.ReLU(inplace=True),
    )


class DeepLabV3PlusDecoder(nn.Module):
    """Merge the ASPP output with projected stride-4 features, then refine with 3x3 convs.

    Args:
        low_channels: channels of the stride-4 backbone features.
        aspp_channels: channels of the ASPP output.
        channels: width of the 3x3 conv-BN-ReLU blocks (256 in the paper).
        num_convs: number of 3x3 blocks: 2 in the paper, 1 in VainF/DeepLabV3Plus-Pytorch.

    Example:
        >>> dec = DeepLabV3PlusDecoder(low_channels=24, aspp_channels=64, channels=32)
        >>> dec(torch.rand(2, 64, 4, 8), torch.rand(2, 24, 16, 32)).shape
        torch.Size([2, 32, 16, 32])
    """

    def __init__(
        self, low_channels: int, aspp_channels: int, channels: int, num_convs: int = 2
    ) -> None:
        super().__init__()
        self.project = _conv_bn_relu(low_channels, LOW_LEVEL_CHANNELS, 1)
        self.fuse = nn.Sequential(
            _conv_bn_relu(aspp_channels + LOW_LEVEL_CHANNELS, channels, 3),
            *(_conv_bn_relu(channels, channels, 3) for _ in range(num_convs - 1)),
        )

    def forward(self, high: torch.Tensor, low: torch.Tensor) -> torch.Tensor:
        """(B, aspp_channels, h, w) and (B, low_channels, H/4, W/4) → (B, channels, H/4, W/4)."""
        high = F.interpolate(high, size=low.shape[-2:], mode="bilinear", align_corners=False)
        return self.fuse(torch.cat([high, self.project(low)], dim=1))


class DeepLabV3Plus(nn.Module):
    """DeepLabv3+: a backbone, ASPP, the v3+ decoder and a 1x1 classifier.

    Args:
        num_classes: number of output channels (logits).
        backbone: one of `BACKBONES`.
        output_stride: 32, 16 or 8 (ResNets), 16 (mobilenet_v3_large); ASPP rates follow it.
        backbone_weights: optional path to a torchvision classification state dict for the
            backbone (its ``fc.*`` / ``classifier.*`` head is ignored); nothing is downloaded.
            The ResNets are costseg's own (`costseg.models.resnet`) under torchvision's names.
        decoder_channels: width of the ASPP output and of the decoder convs (256 in the paper);
            smaller values make a cheaper head for CPU training.
        decoder_convs: 3x3 conv blocks after the merge: 2 (the paper), or 1 (the layout of
            VainF/DeepLabV3Plus-Pytorch checkpoints, see ``costseg.networks``).

    Raises:
        ValueError: unknown backbone, unsupported stride, bad sizes, or weights that do not match.
        FileNotFoundError: ``backbone_weights`` does not exist.

    Example:
        >>> net = DeepLabV3Plus(num_classes=19, backbone="resnet18", decoder_channels=32)
        >>> net(torch.rand(2, 3, 33, 47)).shape
        torch.Size([2, 19, 33, 47])
    """

    def __init__(
        self,
        num_classes: int,
        backbone: str = "resnet50",
        output_stride: int = 16,
        backbone_weights: str | Path | None = None,
        decoder_channels: int = 256,
        decoder_convs: int = 2,
    ) -> None:
        super().__init__()
        spec = _validated_spec(num_classes, backbone, output_stride, decoder_channels)
        if decoder_convs < 1:
            raise ValueError(f"decoder_convs must be a positive integer; got {decoder_convs!r}")
        self.init_args = {  # what rebuilds this network (a checkpoint's model.net entry)
            "num_classes": num_classes,
            "backbone": backbone,
            "output_stride": output_stride,
            "backbone_weights": None if backbone_weights is None else str(backbone_weights),
            "decoder_channels": decoder_channels,
            "decoder_convs": decoder_convs,
        }
        self.output_stride = output_stride
        self.backbone = spec.build(output_stride)
        self.aspp = ASPP(spec.high_channels, ATROUS_RATES[output_stride], decoder_channels)
        self.decoder = DeepLabV3PlusDecoder(
            spec.low_channels, decoder_channels, decoder_channels, decoder_convs
        )
        self.classifier = nn.Conv2d(decoder_channels, num_classes, 1)
        for head in (self.aspp, self.decoder, self.classifier):
            _init_head(head)
        if backbone_weights is not None:
            load_backbone_weights(self.backbone, backbone_weights)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """(B, 3, H, W) normalised images → (B, num_classes, H, W) logits."""
        features = self.backbone(x)
        y = self.decoder(self.aspp(features["out"]), features["low"])
        y = self.classifier(y)
        return F.interpolate(y, size=x.shape[-2:], mode="bilinear", align_corners=False)


def _validated_spec(
    num_classes: int, backbone: str, output_stride: int, decoder_channels: int
) -> _BackboneSpec:
    if backbone not in _SPECS:
        raise ValueError(f"backbone must be one of {', '.join(BACKBONES)}; got {backbone!r}")
    spec = _SPECS[backbone]
    if output_stride not in spec.output_strides:
        valid = " or ".join(str(s) for s in spec.output_strides)
        raise ValueError(f"output_stride for {backbone} must be {valid}; got {output_stride!r}")
    if num_classes < 1 or decoder_channels < 1:
        raise ValueError(
            "num_classes and decoder_channels must be positive integers; "
            f"got {num_classes!r} and {decoder_channels!r}"
        )
    return spec


def _init_head(module: nn.Module) -> None:
    """Kaiming init for new convs; BN starts as the identity (weight 1, bias 0)."""
    for m in module.modules():
        if isinstance(m, nn.Conv2d):
            nn.init.kaiming_normal_(m.weight, mode="fan_out", nonlinearity="relu")
            if m.bias is not None:
                nn.init.zeros_(m.bias)
        elif isinstance(m, nn.BatchNorm2d):
            nn.init.ones_(m.weight)
            nn.init.zeros_(m.bias)


def load_backbone_weights(backbone: nn.Module, path: str | Path) -> None:
    """Load a torchvision classification state dict into ``backbone``, ignoring its head.

    Every backbone key must be present with the same shape, and no key other than the
    ``fc.*`` / ``classifier.*`` head may be left over.

    Args:
        backbone: the feature extractor (``DeepLabV3Plus.backbone``).
        path: a file written by ``torch.save(model.state_dict(), path)``.

    Raises:
        FileNotFoundError: ``path`` does not exist.
        ValueError: the file is not a state dict, or its keys or shapes do not match.

    Example:
        >>> import tempfile
        >>> net = DeepLabV3Plus(19, "resnet18", decoder_channels=32)
        >>> state = {**net.backbone.state_dict(), "fc.weight": torch.zeros(1000, 512)}
        >>> with tempfile.TemporaryDirectory() as tmp:
        ...     torch.save(state, f"{tmp}/r18.pth")
        ...     load_backbone_weights(net.backbone, f"{tmp}/r18.pth")
    """
    path = Path(path)
    state = _read_state_dict(path)
    state = {k: v for k, v in state.items() if not str(k).startswith(_HEAD_PREFIXES)}
    expected = backbone.state_dict()
    missing = sorted(set(expected) - set(state))
    unexpected = sorted(set(state) - set(expected))
    if missing or unexpected:
        raise ValueError(
            f"{path} does not match the backbone: {len(missing)} missing keys "
            f"(e.g. {missing[:3]}), {len(unexpected)} unexpected keys (e.g. {unexpected[:3]})"
        )
    wrong = [k for k, v in expected.items() if getattr(state[k], "shape", None) != v.shape]
    if wrong:
        raise ValueError(f"{path} has {len(wrong)} tensors of the wrong shape, e.g. {wrong[0]!r}")
    backbone.load_state_dict(state, strict=True)


def _read_state_dict(path: Path) -> dict[str, torch.Tensor]:
    if not path.is_file():
        raise FileNotFoundError(f"backbone weights file not found: {path}")
    state = read_torch_file(path)
    if not isinstance(state, dict):
        raise ValueError(f"{path} should hold a state dict; got a {type(state).__name__}")
    return state
