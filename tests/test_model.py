"""Tests for costseg.models.deeplabv3plus: shapes, strides, gradients, weight loading, errors."""

from __future__ import annotations

import math
from pathlib import Path

import pytest
import torch
from torch import nn
from torch.nn import functional as F
from torchvision import models

from costseg.models.deeplabv3plus import BACKBONES, DeepLabV3Plus, load_backbone_weights

pytestmark = pytest.mark.usefixtures("one_thread")


# Both strides where supported, and the odd size that checks the final resize.
CASES = [
    ("resnet18", 16, (64, 128)),
    ("resnet18", 8, (65, 97)),
    ("mobilenet_v3_large", 16, (64, 128)),
    ("mobilenet_v3_large", 16, (65, 97)),
]


def _record_io(module: nn.Module, store: dict[str, tuple[torch.Tensor, ...]], key: str) -> None:
    """Keep (*inputs, output) of each call of ``module`` under ``store[key]``."""
    module.register_forward_hook(lambda _m, args, out: store.__setitem__(key, (*args, out)))


@pytest.mark.parametrize(("backbone", "stride", "size"), CASES)
def test_forward_backward_shapes_and_strides(
    backbone: str, stride: int, size: tuple[int, int]
) -> None:
    torch.manual_seed(0)
    net = DeepLabV3Plus(num_classes=5, backbone=backbone, output_stride=stride, decoder_channels=32)
    seen: dict[str, tuple[torch.Tensor, ...]] = {}
    for key in ("aspp", "decoder", "classifier"):
        _record_io(getattr(net, key), seen, key)
    h, w = size
    logits = net(torch.randn(2, 3, h, w))

    assert logits.shape == (2, 5, h, w)
    # Padded convolutions round up: a stride-s map of an HxW input is ceil(H/s) x ceil(W/s).
    assert seen["aspp"][0].shape[-2:] == (math.ceil(h / stride), math.ceil(w / stride))
    assert seen["decoder"][1].shape[-2:] == (math.ceil(h / 4), math.ceil(w / 4))
    stride4_logits = seen["classifier"][1]
    assert stride4_logits.shape == (2, 5, math.ceil(h / 4), math.ceil(w / 4))
    expected = F.interpolate(stride4_logits, size=(h, w), mode="bilinear", align_corners=False)
    torch.testing.assert_close(logits, expected)

    F.cross_entropy(logits, torch.randint(0, 5, (2, h, w))).backward()
    for name, p in net.named_parameters():
        assert p.grad is not None, name
        assert torch.isfinite(p.grad).all(), name
    stem = next(p for name, p in net.backbone.named_parameters() if name.endswith("weight"))
    assert stem.grad is not None and stem.grad.abs().sum() > 0


@pytest.mark.parametrize("stride", [16, 8])
def test_resnet50_stride(stride: int) -> None:
    net = DeepLabV3Plus(num_classes=3, backbone="resnet50", output_stride=stride).eval()
    seen: dict[str, tuple[torch.Tensor, ...]] = {}
    _record_io(net.aspp, seen, "aspp")
    with torch.no_grad():
        net(torch.randn(1, 3, 32, 32))
    assert seen["aspp"][0].shape[-2:] == (32 // stride, 32 // stride)


@pytest.mark.parametrize(
    ("stride", "dilations", "rates"), [(16, (1, 2), (6, 12, 18)), (8, (2, 4), (12, 24, 36))]
)
def test_basic_block_dilation_and_aspp_rates(
    stride: int, dilations: tuple[int, int], rates: tuple[int, ...]
) -> None:
    net = DeepLabV3Plus(num_classes=3, backbone="resnet18", output_stride=stride)
    for stage, dilation in zip(("layer3", "layer4"), dilations, strict=True):
        convs = [m for m in getattr(net.backbone, stage).modules() if isinstance(m, nn.Conv2d)]
        assert all(c.stride == (1, 1) for c in convs) == (dilation > 1)
        assert {c.dilation for c in convs if c.kernel_size == (3, 3)} == {(dilation, dilation)}
    assert tuple(branch[0].dilation[0] for branch in net.aspp.convs[1:4]) == rates


def test_decoder_layout_and_head_init() -> None:
    torch.manual_seed(0)
    net = DeepLabV3Plus(num_classes=19, backbone="resnet18")
    project, fuse = net.decoder.project[0], net.decoder.fuse[0][0]
    assert (project.in_channels, project.out_channels, project.kernel_size) == (64, 48, (1, 1))
    assert (fuse.in_channels, fuse.out_channels, fuse.kernel_size) == (256 + 48, 256, (3, 3))
    for head in (net.aspp, net.decoder):
        for m in head.modules():
            if isinstance(m, nn.BatchNorm2d):
                assert torch.equal(m.weight, torch.ones_like(m.weight))
                assert torch.equal(m.bias, torch.zeros_like(m.bias))
    conv = net.decoder.fuse[1][0]  # 256 -> 256, 3x3: kaiming fan_out std = sqrt(2 / (256 * 9))
    assert conv.weight.std().item() == pytest.approx(math.sqrt(2 / (256 * 9)), rel=0.02)
    assert torch.equal(net.classifier.bias, torch.zeros(19))


@pytest.mark.parametrize(
    ("backbone", "head"), [("resnet18", "fc."), ("mobilenet_v3_large", "classifier.")]
)
def test_backbone_weights_round_trip(tmp_path: Path, backbone: str, head: str) -> None:
    torch.manual_seed(1)
    source = getattr(models, backbone)(weights=None)
    with torch.no_grad():  # distinct values everywhere, BN statistics included
        for t in source.state_dict().values():
            if t.is_floating_point():
                t.copy_(torch.randn_like(t))
    path = tmp_path / f"{backbone}.pth"
    torch.save(source.state_dict(), path)

    net = DeepLabV3Plus(num_classes=19, backbone=backbone, backbone_weights=path)
    loaded = net.backbone.state_dict()
    saved = {k: v for k, v in source.state_dict().items() if not k.startswith(head)}
    assert loaded.keys() == saved.keys()
    for key, value in saved.items():
        assert torch.equal(loaded[key], value), key


def test_unknown_backbone_lists_valid_ones() -> None:
    names = ("resnet18", "resnet18_w32", "resnet34", "resnet50", "resnet101", "mobilenet_v3_large")
    with pytest.raises(ValueError, match=", ".join(names)):
        DeepLabV3Plus(num_classes=19, backbone="xception")
    assert names == BACKBONES


def test_half_width_resnet18_has_a_quarter_of_the_convolution_weights() -> None:
    """Every conv of ResNet-18 at base width 32 has half the input and output channels of
    torchvision's (the stem's input: 3), so its conv weights are a quarter (the stem's a half)."""
    from torchvision.models import resnet18

    from costseg.models.resnet import ResNetTrunk

    def conv_weights(net: torch.nn.Module) -> list[int]:
        return [m.weight.numel() for m in net.modules() if isinstance(m, torch.nn.Conv2d)]

    full, half = conv_weights(resnet18()), conv_weights(ResNetTrunk("resnet18", 32, width=32))
    assert half[0] * 2 == full[0]
    assert [4 * n for n in half[1:]] == full[1:]


@pytest.mark.parametrize(
    ("backbone", "stride", "message"),
    [
        ("resnet18", 4, "must be 8 or 16 or 32; got 4"),
        ("mobilenet_v3_large", 8, "must be 16; got 8"),
    ],
)
def test_unsupported_stride(backbone: str, stride: int, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        DeepLabV3Plus(num_classes=19, backbone=backbone, output_stride=stride)


def test_bad_sizes() -> None:
    with pytest.raises(ValueError, match="positive"):
        DeepLabV3Plus(num_classes=0, backbone="resnet18")


def test_missing_weights_file(tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError, match=r"nope\.pth"):
        DeepLabV3Plus(19, "resnet18", backbone_weights=tmp_path / "nope.pth")


def test_weights_that_do_not_match(tmp_path: Path) -> None:
    backbone = DeepLabV3Plus(19, "resnet18", decoder_channels=8).backbone
    r18 = models.resnet18(weights=None).state_dict()
    mobilenet = models.mobilenet_v3_large(weights=None).state_dict()
    cases = [
        (mobilenet, "does not match the backbone: 120 missing keys"),
        ({**r18, "layer5.weight": torch.zeros(1)}, "0 missing keys .* 1 unexpected keys"),
        ({**r18, "conv1.weight": torch.zeros(64, 3, 3, 3)}, "wrong shape, e.g. 'conv1.weight'"),
        ([1, 2], "should hold a state dict; got a list"),
    ]
    for i, (content, message) in enumerate(cases):
        path = tmp_path / f"{i}.pth"
        torch.save(content, path)
        with pytest.raises(ValueError, match=message):
            load_backbone_weights(backbone, path)
    (tmp_path / "junk.pth").write_bytes(b"not a checkpoint")
    with pytest.raises(ValueError, match=r"junk\.pth is not a readable torch file"):
        load_backbone_weights(backbone, tmp_path / "junk.pth")
