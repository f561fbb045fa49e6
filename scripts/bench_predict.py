"""Speed of predict.py, as ratios measured side by side in one run.

    python scripts/bench_predict.py [--images 3] [--explorer PAGE]

Per image size (1024 × 2048 and the toy 128 × 256), the time predict.py takes per image with
four rules (robotistic, altruistic, egoistic, ml: reading the PNG, the network, the rules,
panels, PNGs and counts) ÷ the network's own forward pass on the same image, on the CPU, with
the toy configuration's network (DeepLabv3+ ResNet-18; untrained weights run as fast) on
stand-in images. With ``--explorer PAGE``: the page's own "ms" of one recomputation in headless
Chromium (the best of 5 loads, each after 3 recomputations) and the page's size.
"""

from __future__ import annotations

import re
import shutil
import statistics
import subprocess
import tempfile
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from PIL import Image

from costseg.classes import CLASS_NAMES
from costseg.cli import parse_options
from costseg.data.prior_maps import PriorMaps
from costseg.models.deeplabv3plus import DeepLabV3Plus
from costseg.networks.base import ImageNetwork
from costseg.networks.sources import Source
from costseg.options import PredictOptions, option
from costseg.prediction.inputs import find_inputs
from costseg.prediction.job import PredictPlan, run
from costseg.rules import parse_rules
from costseg.values import whole_number

RULES = ["robotistic", "altruistic", "egoistic", "ml"]


def forward_seconds(net: torch.nn.Module, image: np.ndarray, repeats: int) -> float:
    x = torch.from_numpy(image).permute(2, 0, 1)[None].contiguous()
    times = []
    with torch.inference_mode():
        for _ in range(repeats + 1):
            start = time.perf_counter()
            net(x)
            times.append(time.perf_counter() - start)
    return statistics.median(times[1:])


def predict_seconds(net: torch.nn.Module, paths: list[Path], out: Path) -> float:
    opts = PredictOptions(input=[str(paths[0].parent)], cost=RULES, progress=False)
    priors = torch.rand(len(CLASS_NAMES), 64, 128).softmax(0)
    job = PredictPlan(
        options=opts,
        inputs=find_inputs(paths),
        device=torch.device("cpu"),
        source=Source("network", {"network": "bench"}, network=net),
        rules=parse_rules(RULES),
        output_dir=out,
        priors=PriorMaps(priors),
    )
    run(PredictPlan(**{**vars(job), "inputs": find_inputs(paths[:1])}))  # warm-up (numba, caches)
    start = time.perf_counter()
    run(PredictPlan(**{**vars(job), "output_dir": out / "timed"}))
    return (time.perf_counter() - start) / len(paths)


def bench_size(net: torch.nn.Module, size: tuple[int, int], images: int) -> tuple[float, float]:
    rng = np.random.default_rng(0)
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp) / "images"
        folder.mkdir()
        paths = []
        for i in range(images):
            image = rng.integers(0, 256, (*size, 3), dtype=np.uint8)
            Image.fromarray(image).save(folder / f"stand_in_{i}.png")
            paths.append(folder / f"stand_in_{i}.png")
        forward = forward_seconds(net, image, max(2, images))
        per_image = predict_seconds(net, paths, Path(tmp) / "out")
    return per_image, forward


def page_ms(page: Path, runs: int = 5) -> float:
    chromium = shutil.which("chromium") or shutil.which("google-chrome")
    found = []
    for _ in range(runs):
        dom = subprocess.run(
            [chromium, "--headless", "--no-sandbox", "--disable-gpu", "--dump-dom",
             f"{page.resolve().as_uri()}#w=0.3,0.3,0.4&clicks=3"],
            capture_output=True, text=True, timeout=300,
        ).stdout  # fmt: skip
        found += [float(m) for m in re.findall(r'"ms":([0-9.]+)', dom)]
    return min(found)


@dataclass
class PredictBenchOptions:
    """What ``bench_predict.py`` can be told (``--help``)."""

    images: int = option(
        3, "1024 x 2048 images timed (ten times as many at 128 x 256)", type=whole_number(1)
    )
    explorer: Path | None = option(
        help="an explorer.html to time in Chromium", type=Path, metavar="PAGE"
    )


def main(args: Sequence[str] | None = None) -> None:
    args = parse_options(PredictBenchOptions, args, "bench_predict.py", __doc__.splitlines()[0])
    net = ImageNetwork(
        DeepLabV3Plus(num_classes=19, backbone="resnet18", decoder_channels=128), channels_last=True
    )
    print(f"torch threads: {torch.get_num_threads()}")
    print(f"{'size':>12} {'predict s/img':>14} {'forward s/img':>14} {'ratio':>6}")
    for size, images in (((1024, 2048), args.images), ((128, 256), 10 * args.images)):
        per_image, forward = bench_size(net, size, images)
        label = f"{size[0]}x{size[1]}"
        print(f"{label:>12} {per_image:14.3f} {forward:14.3f} {per_image / forward:6.2f}")
    if args.explorer:
        size = args.explorer.stat().st_size / 2**20
        print(f"explorer: {page_ms(args.explorer):.0f} ms per recomputation, {size:.1f} MiB page")


if __name__ == "__main__":
    main()
