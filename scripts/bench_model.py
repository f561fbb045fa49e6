"""CPU training-step throughput of the packaged toy recipes, in images/s, side by side.

Each recipe is read from its packaged config (``toy``: the demo; ``toy_long``: the longer recipe)
and timed in float32; ``toy_long`` also in bf16 autocast, to show what bf16 costs on this CPU
(emulated, and many times slower, where the CPU has no native bf16). One step
= forward, cross-entropy, backward, AdamW update, on a fixed random batch of the config's size and
batch size, in the memory format the training module uses. Every configuration is warmed up
once, then the timed steps go round-robin over the configurations, so that a change in the load
of a shared machine hits all of them alike; the median step time is reported.

    python scripts/bench_model.py [--threads 2] [--steps 3] [--no-bf16]
"""

from __future__ import annotations

import os
import statistics
import time
from collections.abc import Sequence
from dataclasses import dataclass

import torch
import yaml
from torch.nn import functional as F

from costseg import CONFIGS
from costseg.classes import IGNORE_INDEX, NUM_CLASSES
from costseg.cli import parse_options
from costseg.models.deeplabv3plus import DeepLabV3Plus
from costseg.options import option
from costseg.values import whole_number


@dataclass
class ModelBenchOptions:
    """What ``bench_model.py`` can be told (``--help``)."""

    threads: int = option(2, "torch intra-op threads", type=whole_number(1))
    steps: int = option(3, "timed steps per configuration", type=whole_number(1))
    bf16: bool = option(True, "skip the bf16 autocast step", flag="--no-bf16")


@dataclass(frozen=True)
class Recipe:
    """One config's network, input size and batch, in one precision."""

    config: str
    backbone: str
    output_stride: int
    decoder_channels: int
    size: tuple[int, int]
    batch: int
    bf16: bool = False

    @classmethod
    def read(cls, config: str, bf16: bool = False) -> Recipe:
        text = yaml.safe_load((CONFIGS / f"{config}.yaml").read_text())
        model, data = text["model"]["net"]["init_args"], text["data"]["init_args"]
        return cls(
            config,
            model["backbone"],
            model["output_stride"],
            model["decoder_channels"],
            tuple(data["size"]),
            data["batch_size"],
            bf16,
        )

    def __str__(self) -> str:
        h, w = self.size
        dtype = "bf16" if self.bf16 else "fp32"
        return (
            f"{self.config:<9} {self.backbone} os{self.output_stride} dc{self.decoder_channels:<3}"
            f" {h}x{w} batch {self.batch} {dtype}"
        )


class Step:
    """A model, its optimiser and one fixed random batch."""

    def __init__(self, recipe: Recipe) -> None:
        self.bf16 = recipe.bf16
        self.net = DeepLabV3Plus(
            NUM_CLASSES, recipe.backbone, recipe.output_stride, None, recipe.decoder_channels
        ).to(memory_format=torch.channels_last)
        self.optimizer = torch.optim.AdamW(self.net.parameters(), lr=1e-3)
        images = torch.randn(recipe.batch, 3, *recipe.size)
        self.images = images.contiguous(memory_format=torch.channels_last)
        self.labels = torch.randint(0, NUM_CLASSES, (recipe.batch, *recipe.size))
        self.labels[:, :8] = IGNORE_INDEX  # some ignored pixels, as in real labels

    def __call__(self) -> float:
        """Run one training step; return its wall time in seconds."""
        start = time.perf_counter()
        self.optimizer.zero_grad(set_to_none=True)
        with torch.autocast("cpu", torch.bfloat16, enabled=self.bf16):
            logits = self.net(self.images)
        loss = F.cross_entropy(logits.float(), self.labels, ignore_index=IGNORE_INDEX)
        loss.backward()
        self.optimizer.step()
        return time.perf_counter() - start


def main(args: Sequence[str] | None = None) -> None:
    """Time every recipe and print one line each, with its speed relative to the first."""
    args = parse_options(ModelBenchOptions, args, "bench_model.py", __doc__.splitlines()[0])
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    recipes = [Recipe.read("toy_long"), Recipe.read("toy")]
    if args.bf16:
        recipes.insert(0, Recipe.read("toy_long", bf16=True))
    print(
        f"threads {args.threads}, {args.steps} timed steps, "
        f"load average before {os.getloadavg()[0]:.1f}"
    )
    steps = [Step(recipe) for recipe in recipes]
    for step in steps:
        step()  # warm-up: allocator and kernel selection
    times: list[list[float]] = [[] for _ in steps]
    for _ in range(args.steps):
        for step, record in zip(steps, times, strict=True):
            record.append(step())
    rates = [r.batch / statistics.median(t) for r, t in zip(recipes, times, strict=True)]
    for recipe, record, rate in zip(recipes, times, rates, strict=True):
        seconds = statistics.median(record)
        print(
            f"{recipe}: {rate:6.2f} images/s ({seconds:.2f} s/step), "
            f"{rate / rates[0]:.2f}x the first"
        )
    print(f"load average after {os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    main()
