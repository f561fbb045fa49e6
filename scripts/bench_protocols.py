"""Speed of the inference protocols (docs/definitions.md §13), as ratios measured side by side.

    python scripts/bench_protocols.py [--threads 2] [--repeats 5] [--size 128 256]

Per image, on the CPU, with the demo's network (configs/toy.yaml: DeepLabv3+ on a half-width
ResNet-18, output stride 32; random weights run as fast as trained ones) on a stand-in image: the
time of each protocol's probabilities ÷ one whole-image forward, for the whole image, sliding
windows (a crop of half the image, stride 3/4 of the crop), flip, and three scales with flip. The
rules run once on the final map whatever the protocol (as do the metrics, which need labels and
are not timed here): the last columns add one pass of the three named rules to each. The
protocols are built as evaluate.py and predict.py build them (``with_protocol``); the timed
calls go round-robin over the protocols, so that a change in the load of a shared machine hits
all of them alike, and the median is reported.
"""

from __future__ import annotations

import os
import statistics
import time
from collections.abc import Sequence
from dataclasses import dataclass

import torch
import yaml

from costseg import CONFIGS
from costseg.classes import NUM_CLASSES
from costseg.cli import parse_options
from costseg.models.entries import network_from_entry
from costseg.networks.base import ImageNetwork
from costseg.networks.protocols import Protocol, with_protocol
from costseg.networks.sources import Source
from costseg.options import option
from costseg.rules import apply_rules, parse_rules
from costseg.values import whole_number

RULES = ["robotistic", "altruistic", "egoistic"]


@dataclass
class ProtocolBenchOptions:
    """What ``bench_protocols.py`` can be told (``--help``)."""

    threads: int = option(2, "torch intra-op threads", type=whole_number(1))
    repeats: int = option(5, "timed calls per protocol", type=whole_number(1))
    size: list[int] = option(
        [128, 256], "the image's size", type=whole_number(1), nargs=2, metavar=("H", "W")
    )


def demo_network() -> ImageNetwork:
    """The network of configs/toy.yaml with random weights, channels-last as costseg runs it."""
    model = yaml.safe_load((CONFIGS / "toy.yaml").read_text())["model"]
    net = network_from_entry(model["net"], NUM_CLASSES)
    return ImageNetwork(net, channels_last=True)


def protocols(size: tuple[int, int]) -> list[Protocol]:
    """Whole image, slide (crop half the image, stride 3/4 crop), flip, 3 scales + flip."""
    crop = (size[0] // 2, size[1] // 2)
    stride = (crop[0] * 3 // 4, crop[1] * 3 // 4)
    return [
        Protocol(),
        Protocol(crop=crop, stride=stride),
        Protocol(flip=True),
        Protocol(flip=True, scales=(0.75, 1.0, 1.25)),
    ]


def name(protocol: Protocol) -> str:
    """``whole``, ``slide crop 64x128 stride 48x96``, ``flip``, ``flip, scales 0.75/1/1.25``."""
    described = protocol.describe()
    inference = "" if described["inference"] == "whole image" else described["inference"]
    tta = "" if described["tta"] == "none" else described["tta"]
    return "; ".join(filter(None, (inference, tta))) or "whole"


def probabilities(source: Source, image: torch.Tensor) -> torch.Tensor:
    """The probabilities the rules see, as evaluate.py and predict.py make them."""
    scores = source.scores(image, ["stand_in"])
    return scores if source.kind == "probs" else scores.softmax(1)


def timed(function) -> tuple[float, object]:
    start = time.perf_counter()
    value = function()
    return time.perf_counter() - start, value


def main(args: Sequence[str] | None = None) -> None:
    """Time every protocol, then print one line each with its ratios to the whole image."""
    args = parse_options(ProtocolBenchOptions, args, "bench_protocols.py", __doc__.splitlines()[0])
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    size = tuple(args.size)
    net, rules = demo_network(), parse_rules(RULES)
    chosen = protocols(size)
    sources = [
        with_protocol(Source("network", {"network": "demo"}, network=net), p, None, 0)
        for p in chosen
    ]
    image = torch.randint(0, 256, (1, 3, *size), dtype=torch.uint8)
    print(
        f"threads {args.threads}, {size[0]}x{size[1]} image, median of {args.repeats}, "
        f"load average before {os.getloadavg()[0]:.1f}"
    )
    network_s: list[list[float]] = [[] for _ in sources]
    rules_s: list[list[float]] = [[] for _ in sources]
    with torch.inference_mode():
        for source in sources:  # warm-up: allocator, kernel selection, the rules' compilation
            apply_rules(probabilities(source, image), rules)
        for _ in range(args.repeats):
            for k, source in enumerate(sources):
                seconds, probs = timed(lambda s=source: probabilities(s, image))
                network_s[k].append(seconds)
                rules_s[k].append(timed(lambda p=probs: apply_rules(p, rules))[0])
    network = [statistics.median(t) for t in network_s]
    total = [n + statistics.median(r) for n, r in zip(network, rules_s, strict=True)]
    print(f"{'protocol':<32} {'s/img':>7} {'÷ whole':>8} {'+ 3 rules s/img':>16} {'÷ whole':>8}")
    for p, n, t in zip(chosen, network, total, strict=True):
        print(f"{name(p):<32} {n:7.3f} {n / network[0]:8.2f} {t:16.3f} {t / total[0]:8.2f}")
    print(f"load average after {os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    main()
