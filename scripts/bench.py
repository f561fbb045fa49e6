"""Speed of a foreign network with the rules, of saved probabilities, and of training.

    python scripts/bench.py [--skip-network] [--skip-train]

Every figure is timed in the same run (best of several repeats). Sections:

1. one 1024 x 2048 image on the CPU: VainF's ResNet-101 DeepLabV3+ (random weights) with three
   rules, against reading the image's saved float16 probabilities (``--probs``) with the same
   rules;
2. training throughput (images/s) of the default config (the packaged ``toy.yaml``); on a GPU
   also of ``cityscapes.yaml``'s network (crop 768, batch 8, bf16 autocast, channels-last).

The decision layer is timed by scripts/bench_decision.py, the evaluation pipeline by
scripts/bench_pipeline.py.
"""

from __future__ import annotations

import tempfile
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import torch
import yaml
from bench_decision import best_time  # the same timer as the decision benchmark

from costseg import CONFIGS
from costseg.cli import parse_options
from costseg.models.entries import network_from_entry
from costseg.options import option


@dataclass
class BenchOptions:
    """What ``bench.py`` can be told (``--help``)."""

    network: bool = option(True, "skip section 1 (a network and the rules)", flag="--skip-network")
    train: bool = option(True, "skip section 2 (training throughput)", flag="--skip-train")


def bench_network_and_rules(steps: int = 2) -> None:
    """VainF's ResNet-101 DeepLabV3+ (random weights) + three rules per 1024 x 2048 image, and
    reading saved float16 probabilities of such an image from disk instead."""
    from costseg.networks import load_network
    from costseg.networks.probs_files import load_probs, save_probs
    from costseg.networks.vainf import export_vainf_state, vainf_deeplabv3plus
    from costseg.rules import apply_rules, parse_rules

    rules = parse_rules(["robotistic", "altruistic", "egoistic"])
    images = torch.randint(0, 256, (1, 3, 1024, 2048), dtype=torch.uint8)
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "vainf_r101_os16.pth"
        torch.save(
            {"model_state": export_vainf_state(vainf_deeplabv3plus(19, "resnet101", 16))}, path
        )
        net = load_network(f"vainf:{path}")
        with torch.inference_mode():
            probs = net(images).softmax(1)
            t_net = best_time(lambda: apply_rules(net(images).softmax(1), rules), repeats=steps)
            save_probs(Path(tmp) / "image.npz", probs[0])
            t_disk = best_time(
                lambda: apply_rules(
                    load_probs(Path(tmp) / "image.npz", size=(1024, 2048))[None], rules
                ),
                repeats=steps,
            )
    print("one 1024 x 2048 image on the CPU, three rules (robotistic, altruistic, egoistic):")
    print(
        f"  VainF ResNet-101 OS16 network + rules  {t_net:7.2f} s/image ({1 / t_net:.2f} images/s)"
    )
    print(
        f"  saved float16 probabilities + rules    {t_disk:7.2f} s/image "
        f"({1 / t_disk:.2f} images/s)"
    )
    print(f"  --probs speed-up over the network      {t_net / t_disk:7.1f} x")


def bench_training(steps: int = 5) -> None:
    from costseg.data.datamodule import StreetScenesDataModule
    from costseg.training.module import SegmentationModule

    config = yaml.safe_load((CONFIGS / "toy.yaml").read_text())
    model = config["model"]
    net = network_from_entry(model["net"], model["num_classes"], initial_weights=False)
    module = SegmentationModule(**{**model, "net": net})
    data = StreetScenesDataModule(**{**config["data"]["init_args"], "num_workers": 0})
    images, labels = next(iter(_batches(data)))
    optimizer = torch.optim.AdamW(module.parameters(), lr=1e-3)
    precision = str(config["trainer"]["precision"])
    step = _training_step(module.train(), images, labels, optimizer, precision.startswith("bf16"))
    t_step = best_time(step, repeats=steps)
    size = tuple(images.shape[-2:])
    print(
        f"training, default config on the CPU ({net.init_args['backbone']}, {size}, batch "
        f"{len(images)}, {precision}, {torch.get_num_threads()} threads): "
        f"{len(images) / t_step:.1f} images/s"
    )


def bench_training_cuda(steps: int = 10) -> None:
    from costseg.training.module import SegmentationModule

    config = yaml.safe_load((CONFIGS / "cityscapes.yaml").read_text())
    model, data = config["model"], config["data"]["init_args"]
    torch.backends.cudnn.benchmark = True
    net = network_from_entry(model["net"], model["num_classes"], initial_weights=False)
    module = SegmentationModule(**{**model, "net": net}).cuda().train()
    batch, crop = data["batch_size"], data["crop_size"]
    images = torch.randint(0, 256, (batch, 3, crop, crop), dtype=torch.uint8, device="cuda")
    labels = torch.randint(0, model["num_classes"], (batch, crop, crop), device="cuda")
    optimizer = torch.optim.SGD(
        module.parameters(), model["lr"], model["momentum"], weight_decay=model["weight_decay"]
    )
    step = _training_step(module, images, labels, optimizer, bf16=True)
    t_step = best_time(lambda: [step() for _ in range(steps)], 3, torch.cuda.synchronize) / steps
    print(
        f"training, Cityscapes config on {torch.cuda.get_device_name()} "
        f"({net.init_args['backbone']} OS{net.init_args['output_stride']}, crop {crop}, "
        f"batch {batch}, bf16): "
        f"{batch / t_step:.1f} images/s, peak memory "
        f"{torch.cuda.max_memory_allocated() / 2**30:.1f} GiB"
    )


def _training_step(module, images, labels, optimizer, bf16: bool) -> Callable[[], None]:
    """One forward (bf16 autocast or not), cross-entropy, backward and update, as a closure."""

    def step() -> None:
        with torch.autocast(images.device.type, torch.bfloat16, enabled=bf16):
            logits = module(images)
        loss = torch.nn.functional.cross_entropy(logits.float(), labels, ignore_index=255)
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()

    return step


def _batches(data):
    data.setup("fit")
    return data.train_dataloader()


def main(args: Sequence[str] | None = None) -> None:
    opts = parse_options(BenchOptions, args, "bench.py", __doc__.splitlines()[0])
    if opts.network:
        bench_network_and_rules()
    if opts.train:
        bench_training()
        if torch.cuda.is_available():
            bench_training_cuda()


if __name__ == "__main__":
    main()
