"""Measure how fast the procedural street scenes are generated on one thread.

Run ``python scripts/bench_data.py``; prints one line such as
``toy generation: 123.4 images/s at 256x512 (1 thread)``.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass

import torch

from costseg.cli import parse_options
from costseg.data.toy import StreetScenes
from costseg.options import option
from costseg.values import whole_number


@dataclass
class DataBenchOptions:
    """What ``bench_data.py`` can be told (``--help``)."""

    images: int = option(200, "scenes to generate", type=whole_number(1))
    size: list[int] = option(
        [256, 512], "the scenes' size", type=whole_number(1), nargs=2, metavar=("H", "W")
    )


def main(args: Sequence[str] | None = None) -> None:
    args = parse_options(DataBenchOptions, args, "bench_data.py", __doc__.splitlines()[0])
    torch.set_num_threads(1)
    ds = StreetScenes(split="train", length=args.images + 1, size=tuple(args.size), seed=0)
    ds[args.images]  # warm-up: imports, noise bank, caches
    start = time.perf_counter()
    for i in range(args.images):
        ds[i]
    rate = args.images / (time.perf_counter() - start)
    h, w = args.size
    print(f"toy generation: {rate:.1f} images/s at {h}x{w} (1 thread)")


if __name__ == "__main__":
    main()
