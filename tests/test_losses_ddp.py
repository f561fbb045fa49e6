"""A training step under two DDP processes (gloo, CPU) gives each loss and its gradient of one
process on the whole batch, although the processes hold different numbers of valid pixels."""

from __future__ import annotations

import os

import torch
import torch.distributed as dist
import torch.multiprocessing as mp
from test_losses import CLASSES, make_losses
from test_metrics_ddp import free_port
from torch import nn
from torch.nn.parallel import DistributedDataParallel

from costseg.training.losses import batch_mean

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


def worker(rank: int, port: int, expected: list[tuple[float, list[torch.Tensor]]]) -> None:
    os.environ |= {"MASTER_ADDR": "127.0.0.1", "MASTER_PORT": str(port)}
    dist.init_process_group("gloo", rank=rank, world_size=WORLD)
    try:
        images, labels = data()
        half = slice(2 * rank, 2 * rank + 2)
        for loss, (want_loss, want_grads) in zip(make_losses(), expected, strict=True):
            net = DistributedDataParallel(network())
            got_loss, got_grads = step(net, loss, images[half], labels[half])
            name = type(loss).__name__
            assert abs(got_loss - want_loss) <= 1e-6 * abs(want_loss), (name, got_loss, want_loss)
            for got, want in zip(got_grads, want_grads, strict=True):
                torch.testing.assert_close(got, want, rtol=1e-5, atol=1e-7, msg=name)
    finally:
        dist.destroy_process_group()


def test_two_process_training_step_equals_one_process_on_the_whole_batch() -> None:
    images, labels = data()
    expected = [step(network(), loss, images, labels) for loss in make_losses()]
    # the mean of the two halves' own means differs: a per-process mean would fail the test
    cross_entropy, net = make_losses()[0], network()
    halves = [
        batch_mean(cross_entropy(net(images[s]), labels[s]))[0] for s in (slice(0, 2), slice(2, 4))
    ]
    assert abs((halves[0] + halves[1]).item() / 2 - expected[0][0]) > 1e-3
    mp.spawn(worker, args=(free_port(), expected), nprocs=WORLD, join=True)
