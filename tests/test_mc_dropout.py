"""Monte-Carlo dropout (docs/definitions.md §12): seeded and reproducible, batch norm in eval
mode, the plain network when dropout does nothing, refused without dropout layers."""

from __future__ import annotations

import pytest
import torch

from costseg.models.deeplabv3plus import DeepLabV3Plus
from costseg.networks.base import ImageNetwork
from costseg.networks.mc_dropout import MCDropout, dropout_layers, mc_dropout_probs
from costseg.networks.vainf import vainf_deeplabv3plus


@pytest.fixture(scope="module")
def network() -> ImageNetwork:
    torch.manual_seed(0)
    net = DeepLabV3Plus(19, "resnet18", decoder_channels=16)
    with torch.no_grad():  # untrained logits are huge: soften them so that dropout shows
        net.classifier.weight.mul_(0.01)
    return ImageNetwork(net)


@pytest.fixture(scope="module")
def images() -> torch.Tensor:
    return torch.randint(0, 256, (2, 3, 32, 64), generator=torch.Generator().manual_seed(1)).byte()


def test_both_deeplabs_hold_dropout_layers() -> None:
    costseg = DeepLabV3Plus(19, "resnet18", decoder_channels=16)
    assert [m.p for m in dropout_layers(costseg)] == [0.5]  # torchvision's ASPP projection
    assert [m.p for m in dropout_layers(vainf_deeplabv3plus(19, "resnet50", 16))] == [0.1]


def test_seeded_runs_repeat_and_seeds_differ(network, images, one_thread) -> None:
    with torch.inference_mode():
        a = mc_dropout_probs(network, images, 3, seed=4, key="x")
        b = mc_dropout_probs(network, images, 3, seed=4, key="x")
        c = mc_dropout_probs(network, images, 3, seed=5, key="x")
        plain = network(images).softmax(1)
    assert torch.equal(a, b) and not torch.equal(a, c) and not torch.allclose(a, plain)
    torch.testing.assert_close(a.sum(1), torch.ones_like(a[:, 0]))
    assert not network.training and not any(m.training for m in network.modules())


def test_without_active_dropout_it_is_the_plain_network(network, images, one_thread) -> None:
    with torch.inference_mode():
        plain = network(images).softmax(1)
        layers = dropout_layers(network)
        for m in layers:
            m.p = 0.0
        try:
            # batch norm in train mode would use the batch's statistics and differ
            torch.testing.assert_close(mc_dropout_probs(network, images, 3), plain)
        finally:
            for m in layers:
                m.p = 0.5
        plain_net = torch.nn.Sequential(torch.nn.Conv2d(3, 19, 1), torch.nn.BatchNorm2d(19)).eval()
        x = torch.rand(2, 3, 4, 4)
        assert torch.equal(mc_dropout_probs(plain_net, x, 1), plain_net(x).softmax(1))


def test_refused_without_dropout_layers() -> None:
    with pytest.raises(ValueError, match="dropout layers"):
        MCDropout(torch.nn.Conv2d(3, 19, 1), passes=2)
    with pytest.raises(ValueError, match=">= 1"):
        mc_dropout_probs(torch.nn.Dropout(), torch.zeros(1, 2), passes=0)
