"""Measure how fast the procedural street scenes are generated on one thread.

Run ``python scripts/bench_data.py``; prints one line such as
``toy generation: 123.4 images/s at 256x512 (1 thread)``.
"""

from __future__ import annotations

import argparse
import time

import torch

from costseg.data.toy import StreetScenes


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--images", type=int, default=200, help="scenes to generate")
    parser.add_argument("--size", type=int, nargs=2, default=(256, 512), metavar=("H", "W"))
    args = parser.parse_args()
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
