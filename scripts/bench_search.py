"""Time per candidate of a design's search (docs/definitions.md §21), three ways of preparing D1
measured side by side in one run.

    python scripts/bench_search.py --ckpt_path A.ckpt [--root CITYSCAPES_TREE] [--images 25]
        [--candidates 30] [--share 0.1] [--require C1 C2 ...]

The network scores the first --images images of the checkpoint's val split (or of the
Cityscapes-layout tree --root, e.g. one of ``scripts/toy_as_cityscapes.py``), RoIs from its
priors. D1 is then prepared for the fused count pass three ways: **exact**, as ``evaluate.py
--design lagrangian`` prepares it (every pixel that can change a constraint's per-image loss
within the Lagrangian space of --require, and --share of each image's labelled pixels for the
objective); **a sample**, --share of each image's labelled pixels for everything (its per-image
risks are biased: an image whose sample misses a constraint's pixels drops out of that
constraint's mean); and **every pixel**. Each then scores the same --candidates random matrices
of the space (log μ uniform in its box, seeded). Printed: the pixels each keeps, the time to
prepare them, the time per candidate and its ratio to the sample's, and the D1 risks of the
first candidate (argmax) each gives.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch
from study_design import probabilities  # the study's images, read the same way

from costseg.calibration.guarantee import defined_risks
from costseg.cli import parse_options, user_errors
from costseg.decision import count_decisions, prepare_counts, subsample
from costseg.evaluation.analyses.design import SearchImages, pixel_seeds, spaces
from costseg.evaluation.settings import design_settings
from costseg.metrics.requirements import Requirements
from costseg.networks.ensemble import open_sources
from costseg.networks.protocols import Protocol
from costseg.networks.sources import resolve_device
from costseg.options import EvalOptions, option, same_option, whole_number
from costseg.values import share

REQUIRE = ["person:roi1:recall>=0.8", "building:roi3:precision>=0.8", "car:roi1:recall>=0.7"]


@dataclass
class SearchBenchOptions:
    """What ``bench_search.py`` can be told (``--help``)."""

    ckpt_path: list[str] | None = same_option(EvalOptions, "ckpt_path", required=True)
    root: str | None = option(help="a Cityscapes-layout tree (default: the checkpoint's data)")
    images: int = option(25, "val images in D1", type=whole_number(1))
    candidates: int = option(30, "random matrices scored each way", type=whole_number(1))
    pixel_share: float = option(0.1, "of each image's labelled pixels", type=share,
                                flag="--share")  # fmt: skip
    require: list[str] = option(REQUIRE, "the constraints", nargs="+")
    seed: int = same_option(EvalOptions, "seed")
    batch_size: int = same_option(EvalOptions, "batch_size", 2)


def main(args: Sequence[str] | None = None) -> None:
    args = parse_options(SearchBenchOptions, args, "bench_search.py", __doc__.splitlines()[0])
    device = resolve_device("cpu")
    source = open_sources(args.ckpt_path, None, None, device, Protocol(), None, 0)
    seen = probabilities(source, source.data_config, "val", range(args.images), device,
                         args.batch_size, args.root)  # fmt: skip
    req = Requirements.parse(args.require)
    options = EvalOptions(design="lagrangian", require=args.require,
                          design_pixels=args.pixel_share, seed=args.seed)  # fmt: skip
    space = spaces(design_settings(options), req)[0]
    rng = np.random.default_rng(args.seed)
    low, high = np.log(space.low), np.log(space.high)
    matrices = [space.matrix([0.0] * len(args.require))]  # argmax first
    matrices += [space.matrix(np.exp(rng.uniform(low, high, len(args.require))).tolist())
                 for _ in range(args.candidates - 1)]  # fmt: skip

    def exact():
        found = SearchImages.of_images(seen, args.pixel_share, req, [space.hull()], args.seed)
        kept = sum(int((p.inputs.cell >= 0).sum()) for p in found.parts)
        score = found.scorer(req, lambda losses: None)
        return kept, lambda m: score(m)[0]

    def prepared(share_of_pixels: float):
        def make():
            parts, first = [], 0
            for probs, labels, roi in seen:
                if share_of_pixels < 1:
                    seeds = pixel_seeds(args.seed, list(range(first, first + len(labels))))
                    drawn = subsample(probs, labels, roi, share=share_of_pixels, seed=seeds)
                    parts.append(prepare_counts(drawn.probs, drawn.labels, drawn.roi))
                else:
                    parts.append(prepare_counts(probs, labels, roi))
                first += len(labels)
            kept = sum(int((p.cell >= 0).sum()) for p in parts)

            def score(matrix):
                losses = torch.cat(
                    [req.losses(count_decisions(p, matrix).confusion) for p in parts]
                )
                return defined_risks(losses.numpy())[0]

            return kept, score

        return make

    ways = {"exact": exact, f"a {args.pixel_share:.0%} sample": prepared(args.pixel_share),
            "every pixel": prepared(1.0)}  # fmt: skip
    height, width = seen[0][1].shape[-2:]
    print(f"{args.images} images of {height} x {width}, {len(matrices)} candidates of the "
          f"Lagrangian space of {' '.join(args.require)}, "
          f"{torch.get_num_threads()} threads:")  # fmt: skip
    per_candidate = {}
    for name, make in ways.items():
        start = time.perf_counter()
        kept, score = make()
        prepare_s = time.perf_counter() - start
        risks = score(matrices[0])  # also loads the kernels
        start = time.perf_counter()
        for matrix in matrices:
            score(matrix)
        per_candidate[name] = (time.perf_counter() - start) / len(matrices)
        print(f"  {name:14s} {kept:>11,} pixels, prepared in {prepare_s:6.2f} s, "
              f"{1e3 * per_candidate[name]:8.1f} ms a candidate; argmax's D1 risks "
              + ", ".join(f"{r:.4f}" for r in risks))  # fmt: skip
    sample = per_candidate[f"a {args.pixel_share:.0%} sample"]
    print("  per candidate ÷ the sample's: "
          + ", ".join(f"{name} {t / sample:.2f}" for name, t in per_candidate.items()))  # fmt: skip


if __name__ == "__main__":
    with user_errors():
        main()
