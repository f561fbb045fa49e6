"""The decision layer's Triton kernel in several block configurations, side by side on one GPU.

    python scripts/bench_triton_configs.py

On the bench's (1, 19, 1024, 2048) float32 probabilities (``scripts/bench_decision.py``): one
read pass and ``torch.argmax``, then ``decide`` (egoistic) and ``decide_mixtures`` (66 points)
for each (pixels per program, warps) pair of ``triton_kernel.CONFIG``'s candidates; the kernel
alone summing in float64 and in float32 (with the pairs each leaves open); and ``decide`` on an
8 x 8 image, whose time is the per-call overhead. Needs a CUDA GPU.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch
from bench_decision import VERTICES, best_time, probabilities

from costseg.cli import parse_options
from costseg.costs import barycentric_grid
from costseg.decision import decide, decide_mixtures
from costseg.decision.certificate import reference_eps
from costseg.decision.certified import prepare
from costseg.decision.gpu import triton_kernel

# (one matrix, mixtures): pixels per program and warps
CANDIDATES = [((128, 4), (64, 2)), ((256, 2), (128, 4)), ((256, 4), (128, 8)), ((512, 4), (32, 1))]


@dataclass
class TritonBenchOptions:
    """``bench_triton_configs.py`` takes no options but ``--help``."""


def main(args: Sequence[str] | None = None) -> None:
    parse_options(TritonBenchOptions, args, "bench_triton_configs.py", __doc__.splitlines()[0])
    p, sync = probabilities((1, 19, 1024, 2048), "cuda"), torch.cuda.synchronize
    grid = barycentric_grid(0.1)
    print(f"p.sum() {1e3 * best_time(lambda: p.sum(), 20, sync):.4f} ms, "
          f"argmax {1e3 * best_time(lambda: p.argmax(1), 20, sync):.4f} ms")  # fmt: skip
    default = triton_kernel.CONFIG
    for config in CANDIDATES:
        triton_kernel.CONFIG = list(config)
        one = best_time(lambda: decide(p, VERTICES[2]), 20, sync)
        many = best_time(lambda: decide_mixtures(p, VERTICES, grid), 5, sync)
        print(f"decide {config[0]}: {1e3 * one:.4f} ms   mixtures {config[1]}: {1e3 * many:.3f} ms")
    triton_kernel.CONFIG = default
    probs = p.view(19, -1)
    for name, vertices, weights in (
        ("decide", VERTICES[2:3], torch.ones(1, 1)),
        ("mixtures", VERTICES, grid),
    ):
        fast = prepare(vertices.double(), p, None, reference_eps(19, mixtures=True))
        labels = torch.empty(len(weights), probs.shape[1], dtype=torch.uint8, device="cuda")
        for float64 in (True, False):
            rule = triton_kernel.rule(fast.folded, weights, fast.eps, p.device, float64)
            seconds = best_time(lambda r=rule, out=labels: r(probs, out), 10, sync)
            opened = rule(probs, labels)
            count = 0 if opened is None else int(opened.sum())
            print(f"{name} kernel alone, float64={float64}: {1e3 * seconds:.4f} ms, {count} open")
    small = p[:, :, :8, :8].contiguous()
    seconds = best_time(lambda: decide(small, VERTICES[2]), 50, sync)
    print(f"decide on 8 x 8 pixels: {1e3 * seconds:.4f} ms")


if __name__ == "__main__":
    main()
