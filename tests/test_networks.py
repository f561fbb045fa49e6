"""Tests for costseg.networks: VainF and costseg checkpoints, specs and their errors.

The VainF reference below is written from the architecture facts (docs/definitions.md §8):
torchvision ResNet
names, ASPP with a pooling branch and a projection, a 1x1 low-level projection to 48, ONE 3x3
conv on ``[low-level, ASPP]``, a 1x1 classifier and bilinear upsampling. It shares no code with
costseg's `DeepLabV3Plus`.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from torch import nn
from torch.nn import functional as F
from torchvision import models

from costseg.models.deeplabv3plus import DeepLabV3Plus
from costseg.networks import (
    IMAGENET_MEAN,
    IMAGENET_STD,
    LOADERS,
    export_vainf_state,
    load_costseg_checkpoint,
    load_network,
)
from costseg.networks.vainf import vainf_deeplabv3plus

pytestmark = pytest.mark.usefixtures("one_thread")


def _branch(cin: int, cout: int, k: int = 1, dilation: int = 1) -> nn.Sequential:
    pad = dilation if k == 3 else 0
    return nn.Sequential(
        nn.Conv2d(cin, cout, k, padding=pad, dilation=dilation, bias=False),
        nn.BatchNorm2d(cout),
        nn.ReLU(),
    )


class _Pooling(nn.Sequential):
    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = super().forward(x)
        return F.interpolate(y, size=x.shape[-2:], mode="bilinear", align_corners=False)


class _ASPP(nn.Module):
    def __init__(self, cin: int, rates: tuple[int, int, int]) -> None:
        super().__init__()
        pool = _Pooling(nn.AdaptiveAvgPool2d(1), *_branch(cin, 256))
        self.convs = nn.ModuleList(
            [_branch(cin, 256), *(_branch(cin, 256, 3, r) for r in rates), pool]
        )
        self.project = nn.Sequential(*_branch(5 * 256, 256), nn.Dropout(0.1))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.project(torch.cat([conv(x) for conv in self.convs], dim=1))


class _Head(nn.Module):
    def __init__(self, rates: tuple[int, int, int], classes: int) -> None:
        super().__init__()
        self.project = _branch(256, 48)
        self.aspp = _ASPP(2048, rates)
        self.classifier = nn.Sequential(*_branch(304, 256, 3), nn.Conv2d(256, classes, 1))

    def forward(self, low: torch.Tensor, out: torch.Tensor) -> torch.Tensor:
        low = self.project(low)
        high = F.interpolate(
            self.aspp(out), size=low.shape[-2:], mode="bilinear", align_corners=False
        )
        return self.classifier(torch.cat([low, high], dim=1))


class VainFReference(nn.Module):
    """VainF's DeepLabV3+ forward and key layout, written from the facts (normalised input)."""

    def __init__(self, depth: int = 101, output_stride: int = 16, classes: int = 19) -> None:
        super().__init__()
        builder = models.resnet101 if depth == 101 else models.resnet50
        self.backbone = builder(
            weights=None, replace_stride_with_dilation=[False, output_stride == 8, True]
        )
        del self.backbone.avgpool, self.backbone.fc  # VainF keeps layers up to layer4 only
        rates = (6, 12, 18) if output_stride == 16 else (12, 24, 36)
        self.classifier = _Head(rates, classes)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        b = self.backbone
        low = b.layer1(b.maxpool(b.relu(b.bn1(b.conv1(x)))))
        out = b.layer4(b.layer3(b.layer2(low)))
        y = self.classifier(low, out)
        return F.interpolate(y, size=x.shape[-2:], mode="bilinear", align_corners=False)


def _randomise(net: nn.Module, seed: int = 0) -> nn.Module:
    """Random weights and BN statistics measured on random images: every layer's output is
    O(1) and depends on the input, so a swapped channel, a wrong key, stride or padding, or a
    skipped layer changes the logits."""
    gen = torch.Generator().manual_seed(seed)
    for m in net.modules():
        if isinstance(m, nn.Conv2d):
            fan_in = m.weight[0].numel()
            m.weight.data = torch.randn(m.weight.shape, generator=gen) * (2 / fan_in) ** 0.5
            if m.bias is not None:
                m.bias.data = torch.randn(m.bias.shape, generator=gen) * 0.1
        elif isinstance(m, nn.BatchNorm2d):
            m.weight.data = 0.5 + torch.rand(m.num_features, generator=gen)
            m.bias.data = torch.randn(m.num_features, generator=gen) * 0.1
            m.reset_running_stats()
            m.momentum = None  # cumulative average over the calibration batch
    images = torch.randint(0, 256, (4, 3, 64, 80), generator=gen, dtype=torch.uint8)
    with torch.no_grad():
        net.train()(_normalise(images))
    return net.eval()


def _normalise(images: torch.Tensor) -> torch.Tensor:
    mean = torch.tensor(IMAGENET_MEAN).view(1, 3, 1, 1)
    std = torch.tensor(IMAGENET_STD).view(1, 3, 1, 1)
    return (images.float() / 255 - mean) / std


def _images(h: int = 64, w: int = 80, b: int = 1) -> torch.Tensor:
    return torch.randint(
        0, 256, (b, 3, h, w), generator=torch.Generator().manual_seed(1), dtype=torch.uint8
    )


def _save_vainf(path: Path, state: dict[str, torch.Tensor]) -> Path:
    # As VainF's main.py saves it: best_score is a numpy float, which plain weights_only rejects.
    torch.save({"cur_itrs": 3, "model_state": state, "best_score": np.float64(0.7)}, path)
    return path


@pytest.mark.parametrize("depth", [50, 101])
def test_vainf_key_layout_matches_the_reference(depth: int) -> None:
    expected = VainFReference(depth).state_dict()
    ours = export_vainf_state(vainf_deeplabv3plus(19, f"resnet{depth}", 16))
    assert sorted(ours) == sorted(expected)
    assert all(ours[k].shape == v.shape for k, v in expected.items())


@pytest.mark.parametrize(("depth", "stride", "name"), [(101, 16, "x.pth"), (50, 8, "r50_os8.pth")])
def test_vainf_gives_the_reference_logits(
    tmp_path: Path, depth: int, stride: int, name: str
) -> None:
    ref = _randomise(VainFReference(depth, stride))
    path = _save_vainf(tmp_path / name, ref.state_dict())
    net = load_network(f"vainf:{path}")  # stride 16 by default, 8 from the file name
    images = _images(64, 80)
    with torch.no_grad():
        expected, got = ref(_normalise(images)), net(images)
    assert got.shape == (1, 19, 64, 80)
    torch.testing.assert_close(got, expected, atol=1e-5, rtol=1e-4)
    # The stride is not in the weights: the wrong one gives other logits (so the check bites).
    other = load_network(f"vainf:{path}?os={24 - stride}")
    with torch.no_grad():
        assert (other(images) - expected).abs().max() > 1e-3


def test_costseg_network_round_trips_through_vainf_layout(tmp_path: Path) -> None:
    net = _randomise(DeepLabV3Plus(19, "resnet50", 16, decoder_convs=1), seed=3)
    path = _save_vainf(tmp_path / "roundtrip.pth", export_vainf_state(net))
    loaded = load_network(f"vainf:{path}?backbone=resnet50&os=16")
    images = _images(48, 72, b=2)
    with torch.no_grad():
        torch.testing.assert_close(loaded(images), net(_normalise(images)), atol=1e-6, rtol=1e-5)


def test_vainf_errors(tmp_path: Path) -> None:
    state = export_vainf_state(vainf_deeplabv3plus(19, "resnet50", 16))
    renamed = {k.replace("classifier.classifier.3", "classifier.head"): v for k, v in state.items()}
    with pytest.raises(
        ValueError,
        match=r"missing keys \(first: classifier\.classifier\.3\.weight.*"
        r"unexpected keys \(first: classifier\.head\.weight",
    ):
        load_network(f"vainf:{_save_vainf(tmp_path / 'renamed.pth', renamed)}")
    voc = {**state, "classifier.classifier.3.weight": torch.zeros(21, 256, 1, 1)}
    with pytest.raises(ValueError, match="predicts 21 classes; expected the 19"):
        load_network(f"vainf:{_save_vainf(tmp_path / 'voc.pth', voc)}")
    mobile = {"backbone.low_level_features.0.0.weight": torch.zeros(1)}
    with pytest.raises(ValueError, match="MobileNetV2"):
        load_network(f"vainf:{_save_vainf(tmp_path / 'mobile.pth', mobile)}")
    (tmp_path / "text.pth").write_text("not a checkpoint")
    with pytest.raises(ValueError, match=r"text\.pth is not a readable torch file"):
        load_network(f"vainf:{tmp_path / 'text.pth'}")
    torch.save({"model_state": {"a": nn.Linear(1, 1)}}, tmp_path / "module.pth")
    with pytest.raises(ValueError, match="holds objects other than weights"):
        load_network(f"vainf:{tmp_path / 'module.pth'}")
    with pytest.raises(FileNotFoundError, match=r"missing\.pth"):
        load_network(f"vainf:{tmp_path / 'missing.pth'}")


@pytest.mark.parametrize("spec", ["tflite:model.tflite", "model.ckpt", "vainf:", "hf"])
def test_unknown_spec_lists_the_valid_prefixes(spec: str) -> None:
    with pytest.raises(ValueError, match=r"costseg:PATH, vainf:PATH.*segformer:DIR, onnx:FILE"):
        load_network(spec)


def test_every_network_source_has_a_loader_and_its_help():
    from costseg.cli import evaluate_parser
    from costseg.values import NETWORK_SPECS

    assert LOADERS.keys() == NETWORK_SPECS.keys()
    helps = {a.dest: a.help for a in evaluate_parser()._actions}
    assert all(f"{prefix}:{rest}" in helps["network"] for prefix, rest in NETWORK_SPECS.items())


@pytest.mark.parametrize("option", ["os=4", "backbone=resnet18", "depth=50"])
def test_bad_vainf_option(option: str) -> None:
    with pytest.raises(ValueError, match=f"bad option '{option}'"):
        load_network(f"vainf:x.pth?{option}")


def test_decoder_convs_must_be_positive() -> None:
    with pytest.raises(ValueError, match="decoder_convs"):
        DeepLabV3Plus(19, "resnet18", decoder_convs=0)


# ---- costseg checkpoints --------------------------------------------------------------------


def _fake_costseg_checkpoint(path: Path, net: DeepLabV3Plus, classes: list[str]) -> dict:
    """The parts of a train.py checkpoint that loading reads (see module.py)."""
    checkpoint = {
        "state_dict": {f"net.{k}": v for k, v in net.state_dict().items()},
        "hyper_parameters": {
            "num_classes": len(classes),
            "net": {
                "class_path": "costseg.models.deeplabv3plus.DeepLabV3Plus",
                # initial weights named in the entry are not read again (the file is gone)
                "init_args": {**net.init_args, "backbone_weights": "/gone/resnet18.pth"},
            },
            "channels_last": False,
            "_instantiator": "lightning.pytorch.cli.instantiate_module",
        },
        "costseg": {
            "class_names": classes,
            "priors": torch.rand(len(classes), 8, 16),
            "data": {"class_path": "x.Data", "init_args": {"size": (64, 128)}},
        },
    }
    torch.save(checkpoint, path)
    return checkpoint


def test_costseg_checkpoint_without_lightning_objects(tmp_path: Path) -> None:
    from costseg.classes import CLASS_NAMES

    net = _randomise(DeepLabV3Plus(19, "resnet18", decoder_channels=16))
    saved = _fake_costseg_checkpoint(tmp_path / "a.ckpt", net, list(CLASS_NAMES))
    loaded = load_costseg_checkpoint(tmp_path / "a.ckpt")
    images = _images(40, 56)
    with torch.no_grad():
        torch.testing.assert_close(loaded.network(images), net(_normalise(images)), atol=0, rtol=0)
    assert torch.equal(loaded.priors, saved["costseg"]["priors"])
    assert loaded.data_config == saved["costseg"]["data"] and loaded.class_names == CLASS_NAMES
    small = DeepLabV3Plus(2, "resnet18", decoder_channels=16)
    _fake_costseg_checkpoint(tmp_path / "b.ckpt", small, ["road", "sky"])
    with pytest.raises(ValueError, match="trained on 2 classes"):
        load_network(f"costseg:{tmp_path / 'b.ckpt'}")
    torch.save({"state_dict": {}}, tmp_path / "c.ckpt")
    with pytest.raises(ValueError, match="is not a costseg checkpoint"):
        load_costseg_checkpoint(tmp_path / "c.ckpt")


@pytest.mark.parametrize(
    "entry, message",
    [
        (None, "records no network"),
        ({"class_path": "os.system", "init_args": {"command": "exit 3"}}, "not a torch.nn.Module"),
        ({"class_path": "costseg.models.Nothing"}, "cannot import the network"),
    ],
)
def test_a_checkpoint_names_only_a_network_class(tmp_path: Path, entry, message) -> None:
    from costseg.classes import CLASS_NAMES

    net = DeepLabV3Plus(19, "resnet18", decoder_channels=16)
    checkpoint = _fake_costseg_checkpoint(tmp_path / "a.ckpt", net, list(CLASS_NAMES))
    if entry is None:
        del checkpoint["hyper_parameters"]["net"]
    else:
        checkpoint["hyper_parameters"]["net"] = entry
    torch.save(checkpoint, tmp_path / "a.ckpt")
    with pytest.raises(ValueError, match=message):
        load_costseg_checkpoint(tmp_path / "a.ckpt")


def test_costseg_checkpoint_from_train_py(tiny_run) -> None:
    module, _, runs = tiny_run
    path = next(runs.glob("**/last.ckpt"))
    loaded = load_costseg_checkpoint(path)
    images = _images(64, 128, b=2)
    module.eval()
    with torch.no_grad():
        torch.testing.assert_close(loaded.network(images), module(images), atol=1e-6, rtol=1e-5)
    assert torch.equal(loaded.priors, module.priors) and loaded.data_config == module.data_config


def test_loading_a_checkpoint_imports_no_lightning(imported) -> None:
    """Evaluation start-up must not pay for importing Lightning."""
    assert "lightning" not in imported["a checkpoint loaded"]
