"""costseg's ResNet trunks and ASPP against torchvision's, which DeepLabV3Plus used before.

torchvision is imported here only, as the reference: the model itself must not import it (its
import pulls in torch._dynamo, about 2 s of evaluate.py's start-up).
"""

from __future__ import annotations

import dataclasses

import pytest
import torch
from torch import nn
from torchvision import models
from torchvision.models.feature_extraction import create_feature_extractor
from torchvision.models.segmentation.deeplabv3 import ASPP as TorchvisionASPP

from costseg.models import deeplabv3plus
from costseg.models.aspp import ASPP
from costseg.models.deeplabv3plus import DeepLabV3Plus
from costseg.models.resnet import RESNETS, ResNetTrunk

pytestmark = pytest.mark.usefixtures("one_thread")


def _dilate(stage: nn.Module, dilation: int) -> None:
    """git HEAD's conversion of a torchvision BasicBlock stage's stride 2 into dilation."""
    for module in stage.modules():
        if isinstance(module, nn.Conv2d):
            module.stride = (1, 1)
            if module.kernel_size == (3, 3):
                module.dilation = (dilation, dilation)
                module.padding = (dilation, dilation)


def _torchvision_trunk(name: str, output_stride: int) -> nn.Module:
    """The backbone as git HEAD built it, with torchvision."""
    dilate = [False, output_stride == 8, output_stride <= 16]
    builder = getattr(models, name)
    if name in ("resnet50", "resnet101"):
        net = builder(weights=None, replace_stride_with_dilation=dilate)
    else:
        net = builder(weights=None)
        dilation = 1
        for stage, flag in zip((net.layer2, net.layer3, net.layer4), dilate, strict=True):
            if flag:
                dilation *= 2
                _dilate(stage, dilation)
    return create_feature_extractor(net, {"layer1": "low", "layer4": "out"})


def _perturb_batch_norms(module: nn.Module) -> None:
    """Distinct BN affine parameters and running statistics (convs keep their kaiming init)."""
    with torch.no_grad():
        for m in module.modules():
            if isinstance(m, nn.BatchNorm2d):
                m.weight.uniform_(0.5, 1.5)
                m.bias.normal_(0, 0.1)
                m.running_mean.normal_(0, 0.1)
                m.running_var.uniform_(0.5, 1.5)


def _assert_same_state(module: nn.Module, reference: nn.Module) -> None:
    """Same keys in the same order, same shapes and same values."""
    state, expected = module.state_dict(), reference.state_dict()
    assert [(k, v.shape) for k, v in state.items()] == [(k, v.shape) for k, v in expected.items()]
    for key, value in expected.items():
        assert torch.equal(state[key], value), key


# ResNet-101 is the slow one: a smaller image.
SIZES = {"resnet18": (65, 97), "resnet34": (65, 97), "resnet50": (65, 97), "resnet101": (33, 49)}


@pytest.mark.parametrize("stride", [8, 16, 32])
@pytest.mark.parametrize("name", list(RESNETS))
def test_trunk_equals_torchvision(name: str, stride: int) -> None:
    torch.manual_seed(0)
    reference = _torchvision_trunk(name, stride).eval()
    torch.manual_seed(0)
    trunk = ResNetTrunk(name, stride).eval()
    # Same keys in the same order, and the same initial weights from the same seed.
    _assert_same_state(trunk, reference)

    _perturb_batch_norms(reference)
    trunk.load_state_dict(reference.state_dict(), strict=True)
    x = torch.randn(1, 3, *SIZES[name])
    with torch.no_grad():
        expected, got = reference(x), trunk(x)
    assert got.keys() == expected.keys() == {"low", "out"}
    for key in ("low", "out"):
        torch.testing.assert_close(got[key], expected[key])


@pytest.mark.parametrize("rates", [(6, 12, 18), (12, 24, 36)])
def test_aspp_equals_torchvision(rates: tuple[int, int, int]) -> None:
    torch.manual_seed(0)
    reference = TorchvisionASPP(16, rates, 8)
    torch.manual_seed(0)
    aspp = ASPP(16, rates, 8)
    _assert_same_state(aspp, reference)

    _perturb_batch_norms(reference)
    aspp.load_state_dict(reference.state_dict(), strict=True)
    x = torch.randn(2, 16, 9, 13)  # smaller than the rates: padding matters
    with torch.no_grad():
        torch.testing.assert_close(aspp.eval()(x), reference.eval()(x))
        # Training: batch statistics, and dropout draws the same mask from the same seed.
        torch.manual_seed(1)
        got = aspp.train()(x)
        torch.manual_seed(1)
        torch.testing.assert_close(got, reference.train()(x))


@pytest.mark.parametrize("name", list(RESNETS))
def test_network_state_and_logits_equal_the_torchvision_built_one(
    name: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A checkpoint of the torchvision-built network (git HEAD) loads and gives the same logits."""
    torch.manual_seed(0)
    net = DeepLabV3Plus(19, name, output_stride=16, decoder_channels=8).eval()
    # git HEAD's construction: the same DeepLabV3Plus code with torchvision's trunk and ASPP.
    spec = deeplabv3plus._SPECS[name]
    build = lambda stride: _torchvision_trunk(name, stride)  # noqa: E731
    monkeypatch.setitem(deeplabv3plus._SPECS, name, dataclasses.replace(spec, build=build))
    monkeypatch.setattr(deeplabv3plus, "ASPP", TorchvisionASPP)
    torch.manual_seed(0)
    reference = DeepLabV3Plus(19, name, output_stride=16, decoder_channels=8).eval()
    assert isinstance(reference.aspp, TorchvisionASPP)

    _assert_same_state(net, reference)  # a seeded build draws the same weights
    _perturb_batch_norms(reference)
    net.load_state_dict(reference.state_dict(), strict=True)
    x = torch.randn(1, 3, 33, 47)
    with torch.no_grad():
        torch.testing.assert_close(net(x), reference(x))


def test_the_model_imports_no_torchvision(imported) -> None:
    assert "torchvision" not in imported["the model"]
