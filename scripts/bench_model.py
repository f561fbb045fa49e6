"""CPU training-step throughput of DeepLabv3+ configurations, in images/s.

One step = forward (fp32 or bf16 autocast, channels-last as in training), cross-entropy,
backward, SGD update. Every configuration is warmed up once, then the timed steps go round-robin
over the configurations so that a change in the load of a shared machine hits all of them
alike; the median step time is reported.

    python scripts/bench_model.py [--threads 2] [--steps 3] [--batch 8]
"""

from __future__ import annotations

import argparse
import os
import statistics
import time
from dataclasses import dataclass

import torch
from torch.nn import functional as F

from costseg.classes import IGNORE_INDEX, NUM_CLASSES
from costseg.models.deeplabv3plus import DeepLabV3Plus


@dataclass(frozen=True)
class Config:
    """One network and input size to time."""

    backbone: str
    output_stride: int
    decoder_channels: int
    size: tuple[int, int]
    bf16: bool = False

    def __str__(self) -> str:
        h, w = self.size
        dtype = "bf16" if self.bf16 else "fp32"
        return (
            f"{self.backbone:<18} os{self.output_stride} dc{self.decoder_channels:<3} {h}x{w} "
            f"{dtype}"
        )


CONFIGS = (
    Config("resnet18", 16, 256, (128, 256)),
    Config("resnet18", 16, 256, (256, 512)),
    Config("resnet18", 16, 128, (128, 256)),
    Config("resnet18", 16, 128, (128, 256), bf16=True),
    Config("mobilenet_v3_large", 16, 256, (128, 256)),
)


class Trainer:
    """A model, its optimiser and one fixed random batch."""

    def __init__(self, config: Config, batch: int) -> None:
        self.bf16 = config.bf16
        self.net = DeepLabV3Plus(
            NUM_CLASSES, config.backbone, config.output_stride, None, config.decoder_channels
        ).to(memory_format=torch.channels_last)
        self.optimizer = torch.optim.SGD(self.net.parameters(), lr=0.01, momentum=0.9)
        images = torch.randn(batch, 3, *config.size)
        self.images = images.contiguous(memory_format=torch.channels_last)
        self.labels = torch.randint(0, NUM_CLASSES, (batch, *config.size))
        self.labels[:, :8] = IGNORE_INDEX  # some ignored pixels, as in real labels

    def step(self) -> float:
        """Run one training step; return its wall time in seconds."""
        start = time.perf_counter()
        self.optimizer.zero_grad(set_to_none=True)
        with torch.autocast("cpu", torch.bfloat16, enabled=self.bf16):
            logits = self.net(self.images)
        loss = F.cross_entropy(logits.float(), self.labels, ignore_index=IGNORE_INDEX)
        loss.backward()
        self.optimizer.step()
        return time.perf_counter() - start


def main() -> None:
    """Time every configuration and print one line each."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--threads", type=int, default=2, help="torch intra-op threads")
    parser.add_argument("--steps", type=int, default=3, help="timed steps per configuration")
    parser.add_argument("--batch", type=int, default=8, help="images per step")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    print(
        f"threads {args.threads}, batch {args.batch}, {args.steps} timed steps, "
        f"load average before {os.getloadavg()[0]:.1f}"
    )
    trainers = [Trainer(config, args.batch) for config in CONFIGS]
    for trainer in trainers:
        trainer.step()  # warm-up: allocator and kernel selection
    times: list[list[float]] = [[] for _ in trainers]
    for _ in range(args.steps):
        for trainer, record in zip(trainers, times, strict=True):
            record.append(trainer.step())
    for config, record in zip(CONFIGS, times, strict=True):
        seconds = statistics.median(record)
        print(f"{config}: {args.batch / seconds:6.2f} images/s ({seconds:.2f} s/step)")
    print(f"load average after {os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    main()
