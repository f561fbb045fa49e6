"""Compile the numba kernels once and cache them on disk (``make setup`` runs it).

The compiled CPU passes (the decision kernels, a regional value system's runs, the fused
decide-and-count pass, the many-rules
confusion counts, the segment runs,
the segment features of meta classification)
are compiled on first use and cached beside their modules (``cache=True``); without this step the
first evaluation after an install waits for the compiler. Each kernel is compiled for the types
an evaluation gives it, by running the passes on a small synthetic input.

    python -m costseg.compile_kernels
"""

from __future__ import annotations

import time

import torch

from costseg.costs import barycentric_grid, load_cost, mix_costs, with_defer
from costseg.decision import decide, decide_counts, decide_mixtures
from costseg.meta.features import segment_features
from costseg.metrics import RoIPrecisionRecall, SegmentErrors

SIZE = (64, 128)  # a width of a multiple of 64: the segment passes' packed rows


def compile_kernels() -> None:
    """Run every compiled pass once on a small input (each kernel compiles, or loads its cache)."""
    g = torch.Generator().manual_seed(0)
    probs = (4 * torch.randn(2, 19, *SIZE, generator=g)).softmax(1)
    probs[..., :8] = 1 / 19  # ties between mixtures: their settling pass
    vertices = torch.stack([load_cost(n) for n in ("robotistic", "altruistic", "egoistic")])
    weights = barycentric_grid(0.2)  # 21 rules: the many-rules confusion pass
    decide(probs, vertices[2], path="numba")
    roi = torch.randint(0, 5, SIZE, generator=g)
    regional = torch.stack([*vertices, vertices[1], vertices[2]])  # a matrix per RoI
    decide(probs, regional, roi=roi, path="numba")  # the runs of a regional value system
    rules = decide_mixtures(probs, vertices, weights, path="numba")  # uint8 label maps
    decide(probs, mix_costs(vertices, weights)[0], path="numba")
    target = decide(probs, vertices[0])
    target[1][target[1] == 2] = 0  # a class without segments: its arrays' other memory layout
    for cost in (vertices[2], with_defer(vertices[1], 1.0)):  # the fused count pass
        for priors in (None, probs[0] + 0.1):  # q is p; q is p / π (settled in float64)
            decide_counts(probs, cost, target, roi, priors)
    for preds in (rules, rules.long()):
        for region in (None, roi):
            RoIPrecisionRecall(num_rules=len(weights)).update(preds, target, region)
            for classes in ((11,), (11, 2)):
                segments = SegmentErrors(classes, num_rules=len(weights), heatmap_size=(0, 0))
                segments.update(preds, target, region)
    p = probs[0].numpy()
    heat = {"E": p[0]}
    for gt in (None, target[0].numpy()):  # features alone, and with the targets
        segment_features(rules[0, 0].numpy(), p, heat, gt)


if __name__ == "__main__":
    start = time.perf_counter()
    compile_kernels()
    print(f"numba kernels compiled and cached in {time.perf_counter() - start:.0f} s")
