"""Monte-Carlo dropout probabilities (``docs/definitions.md §12``).

The network runs N times with its dropout layers active and everything else, batch norm
included, in evaluation mode; the N softmax outputs are averaged. Each call is seeded by the seed
and a key (the batch's image names), so a run is reproducible and a batch's probabilities do not
depend on what ran before it. Without dropout layers (or with p = 0) every pass is the plain
network, so the mean is its softmax.

>>> net = torch.nn.Sequential(torch.nn.Conv2d(3, 4, 1), torch.nn.Dropout(0.5)).eval()
>>> images = torch.rand(1, 3, 2, 2)
>>> a = mc_dropout_probs(net, images, passes=8, seed=0)
>>> bool(torch.equal(a, mc_dropout_probs(net, images, passes=8, seed=0))), tuple(a.shape)
(True, (1, 4, 2, 2))
>>> net.training                                   # the network's modes are left as they were
False
"""

from __future__ import annotations

import zlib
from collections.abc import Callable, Sequence

import torch
from torch import Tensor, nn

from costseg.networks.uncertainty import RunAverage

DROPOUT_TYPES = (
    nn.Dropout,
    nn.Dropout1d,
    nn.Dropout2d,
    nn.Dropout3d,
    nn.AlphaDropout,
    nn.FeatureAlphaDropout,
)
DEFAULT_SEED = 0


def dropout_layers(network: nn.Module) -> list[nn.Module]:
    """The dropout layers of ``network`` (any of :data:`DROPOUT_TYPES`).

    >>> len(dropout_layers(torch.nn.Sequential(torch.nn.Linear(2, 2), torch.nn.Dropout())))
    1
    """
    return [m for m in network.modules() if isinstance(m, DROPOUT_TYPES)]


def batch_seed(seed: int, key: str = "") -> int:
    """The seed of one call: the CRC-32 of ``seed`` and ``key`` (32 bits: PyTorch's CPU
    generator keeps only the low 32 bits of a seed).

    >>> batch_seed(0, "a") == batch_seed(0, "a") != batch_seed(1, "a")
    True
    """
    return zlib.crc32(f"{int(seed)}\n{key}".encode())


def mc_dropout_probs(
    network: Callable[[Tensor], Tensor] | nn.Module,
    images: Tensor,
    passes: int,
    seed: int = DEFAULT_SEED,
    key: str = "",
) -> Tensor:
    """Mean softmax of ``passes`` forward passes with dropout active, batch norm in eval mode.

    Args:
        network: maps images to (B, N, H, W) logits (e.g. an
            :class:`~costseg.networks.base.ImageNetwork`).
        images: its input batch, e.g. (B, 3, H, W) uint8.
        passes: N >= 1.
        seed: with ``key``, seeds the dropout masks (CPU and CUDA generators alike; the global
            generators are restored afterwards).
        key: what distinguishes this call, e.g. the batch's image names joined.

    Returns:
        (B, N, H, W) float32 probabilities.
    """
    return mc_dropout_runs([network], images, passes, seed, [key], keep_entropy=False).mean


def mc_dropout_runs(
    networks: Sequence[Callable[[Tensor], Tensor] | nn.Module],
    images: Tensor,
    passes: int,
    seed: int,
    keys: Sequence[str],
    keep_entropy: bool = True,
) -> RunAverage:
    """``passes`` runs of several networks (test-time augmentation's views) with dropout active:
    run t is the mean softmax of every network's pass t (``docs/definitions.md §13``).

    Each network's passes draw the masks :func:`mc_dropout_probs` would draw for it alone with
    its key: its generator state is kept between its passes, whatever runs in between.

    Returns:
        the runs' mean probabilities and mean entropy (:class:`RunAverage`).
    """
    if passes < 1:
        raise ValueError(f"passes must be >= 1; got {passes}")
    modules = [m for n in networks if isinstance(n, nn.Module) for m in n.modules()]
    modes = [(m, m.training) for m in modules]
    devices = [images.device.index or 0] if images.device.type == "cuda" else []
    runs = RunAverage(keep_entropy)
    try:
        for m, _ in modes:  # not m.train(): that would also set the children
            m.training = isinstance(m, DROPOUT_TYPES)
        with torch.random.fork_rng(devices=devices):
            states = []
            for key in keys:
                torch.manual_seed(batch_seed(seed, key))
                states.append(_rng_states(devices))
            for _ in range(passes):
                total = None
                for k, network in enumerate(networks):
                    if len(networks) > 1:
                        _set_rng_states(states[k], devices)
                    probs = network(images).float().softmax(1)
                    if len(networks) > 1:
                        states[k] = _rng_states(devices)
                    total = probs if total is None else total + probs
                runs.add(total if len(networks) == 1 else total / len(networks))
    finally:
        for m, training in modes:
            m.training = training
    return runs


def _rng_states(devices: list[int]) -> list[Tensor]:
    """The CPU generator's state, then each CUDA device's."""
    return [torch.get_rng_state(), *(torch.cuda.get_rng_state(d) for d in devices)]


def _set_rng_states(states: list[Tensor], devices: list[int]) -> None:
    torch.set_rng_state(states[0])
    for state, device in zip(states[1:], devices, strict=True):
        torch.cuda.set_rng_state(state, device)


class MCDropout(nn.Module):
    """A network whose output is its Monte-Carlo dropout probabilities (:func:`mc_dropout_probs`).

    Args:
        network: the network (must hold dropout layers).
        passes: N.
        seed: the run's seed.

    Raises:
        ValueError: the network has no dropout layer.
    """

    def __init__(self, network: nn.Module, passes: int, seed: int = DEFAULT_SEED) -> None:
        super().__init__()
        if not dropout_layers(network):
            raise ValueError("--mc_dropout needs dropout layers, and this network has none")
        if passes < 1:
            raise ValueError(f"--mc_dropout must be >= 1; got {passes}")
        self.network, self.passes, self.seed = network, int(passes), int(seed)

    def forward(self, images: Tensor, names: Sequence[str] = ()) -> Tensor:
        """(B, 3, H, W) images (named ``names``, which key the seed) → (B, N, H, W) probs."""
        return mc_dropout_probs(self.network, images, self.passes, self.seed, "\n".join(names))

    def average(
        self, images: Tensor, names: Sequence[str] = (), keep_entropy: bool = True
    ) -> RunAverage:
        """The passes' mean probabilities and mean entropy (the passes are the runs)."""
        key = "\n".join(names)
        return mc_dropout_runs([self.network], images, self.passes, self.seed, [key], keep_entropy)

    def describe(self) -> str:
        """What the probabilities are, for every output."""
        rates = sorted({float(getattr(m, "p", 0.0)) for m in dropout_layers(self.network)})
        return (
            f"Monte-Carlo dropout: mean softmax of {self.passes} passes with dropout active "
            f"(p = {', '.join(f'{r:g}' for r in rates)}; batch norm in eval mode; seed {self.seed})"
        )
