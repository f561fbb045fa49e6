"""A training step under two DDP processes (gloo, CPU) gives each loss and its gradient of one
process on the whole batch, although the processes hold different numbers of valid pixels. The
processes are the ones :mod:`test_metrics_ddp` starts (each spawn costs seconds)."""

from __future__ import annotations

import pytest
import torch
import torch.distributed as dist
from test_losses import CLASSES, make_losses
from torch import nn
from torch.nn.parallel import DistributedDataParallel

from costseg.training.losses import batch_mean

pytestmark = pytest.mark.e2e  # DDP processes

WORLD = 2
PRIORS = torch.tensor([0.4, 0.3, 0.2, 0.1])


def data() -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(0)
    images = torch.randn(4, 3, 6, 8, generator=g)
    labels = torch.randint(0, 3, (4, 6, 8), generator=g)
    labels[:2, :4] = 255  # the first process's half holds a third of the other's valid pixels
    return images, labels


def network() -> nn.Module:
    torch.manual_seed(0)
    return nn.Conv2d(3, len(CLASSES), 1)


def step(net: nn.Module, loss: nn.Module, images, labels) -> tuple[float, list[torch.Tensor]]:
    """One training step's loss (averaged over processes, as Lightning's ``sync_dist`` logs it)
    and the network's gradients."""
    value, _ = batch_mean(loss(net(images), labels, PRIORS))
    value.backward()
    logged = value.detach().clone()
    if dist.is_initialized():
        dist.all_reduce(logged)
        logged /= dist.get_world_size()
    return logged.item(), [p.grad.clone() for p in net.parameters()]


def expected_losses() -> list[tuple[float, list[torch.Tensor]]]:
    """Each loss's step on the whole batch in one process."""
    images, labels = data()
    return [step(network(), loss, images, labels) for loss in make_losses()]


def check_losses(rank: int, expected: list[tuple[float, list[torch.Tensor]]]) -> None:
    """In DDP process ``rank`` (of two): each loss's step on this process's half."""
    images, labels = data()
    half = slice(2 * rank, 2 * rank + 2)
    for loss, (want_loss, want_grads) in zip(make_losses(), expected, strict=True):
        net = DistributedDataParallel(network())
        got_loss, got_grads = step(net, loss, images[half], labels[half])
        name = type(loss).__name__
        assert abs(got_loss - want_loss) <= 1e-6 * abs(want_loss), (name, got_loss, want_loss)
        for got, want in zip(got_grads, want_grads, strict=True):
            torch.testing.assert_close(got, want, rtol=1e-5, atol=1e-7, msg=name)


def test_a_mean_of_per_process_means_would_differ() -> None:
    """The check can fail: the halves' own means average to another loss."""
    images, labels = data()
    cross_entropy, net = make_losses()[0], network()
    halves = [
        batch_mean(cross_entropy(net(images[s]), labels[s]))[0] for s in (slice(0, 2), slice(2, 4))
    ]
    assert abs((halves[0] + halves[1]).item() / 2 - expected_losses()[0][0]) > 1e-3
