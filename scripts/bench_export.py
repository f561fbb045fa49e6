"""Parity and speed of the exported decision graph (docs/deploy.md), side by side in one run.

    python scripts/bench_export.py --cityscapes /tmp/export/cs1024 [--ckpt_path CKPT]
        [--toy_images 8] [--repeats 3] [--output_dir /tmp/export/bench]

Exports the checkpoint (default: the newest ``runs/**/last.ckpt``) once with scripts/export.py's
code, then on the toy validation images (the checkpoint's own dataset) and on the validation
frames of a Cityscapes-layout tree (``scripts/toy_as_cityscapes.py ROOT --size 1024 2048``):

* parity, per rule (robotistic, altruistic, egoistic, ML with the checkpoint's pixel priors,
  Chow's rule deferring at 0.5), all given to the one graph at run time: the pixels whose
  onnxruntime label differs from :func:`decide_reference` on PyTorch's probabilities, and how
  many of those lie beyond the bound of docs/definitions.md §19 (and, apart, how many differ
  from the reference on the graph's own probabilities: float32 decisions alone); the largest
  difference of the log-probabilities (the logits' up to each pixel's softmax constant);
* speed: onnxruntime (CPU) per frame for the network and one rule's decision (egoistic: labels
  and margins) ÷ PyTorch eager (network, softmax, :func:`costseg.decision.decide`), the median
  of ``--repeats`` after a warm-up, both on every core;
* the output's bytes per frame: labels (uint8) and margins (float32) against float32
  probabilities.
"""

from __future__ import annotations

import json
import statistics
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import torch

from costseg.checkpoints import find_checkpoint
from costseg.cli import parse_options, user_errors
from costseg.costs import load_cost, symmetric_cost, with_defer
from costseg.data.from_config import build_dataset
from costseg.data.priors import resize_priors
from costseg.decision import decide
from costseg.export.job import export, plan_export
from costseg.export.parity import parity
from costseg.export.runtime import run_graph
from costseg.networks import load_costseg_checkpoint
from costseg.networks.onnx import onnx_session
from costseg.options import ExportOptions, option
from costseg.values import whole_number

SPEED_RULE = "egoistic"


@dataclass
class ExportBenchOptions:
    """What ``bench_export.py`` can be told (``--help``)."""

    ckpt_path: str | None = option(
        help="a train.py checkpoint (default: the newest)", metavar="PATH"
    )
    cityscapes: Path | None = option(
        help="a 1024 x 2048 tree (scripts/toy_as_cityscapes.py)", type=Path, required=True
    )
    toy_images: int = option(8, "toy validation images", type=whole_number(1))
    frames: int = option(2, "Cityscapes validation frames", type=whole_number(1))
    repeats: int = option(3, "timed frames after a warm-up (their median)", type=whole_number(1))
    output_dir: Path = option(Path("/tmp/export/bench"), "the graph and bench.json", type=Path)


def rules(priors: torch.Tensor) -> dict[str, tuple[torch.Tensor, torch.Tensor | None]]:
    """The rules compared, each (matrix, priors or None)."""
    named = {name: (load_cost(name), None) for name in ("robotistic", "altruistic", "egoistic")}
    named["ml (pixel priors)"] = (symmetric_cost(19), priors)
    named["defer at 0.5 (Chow)"] = (with_defer(symmetric_cost(19), 0.5), None)
    return named


def frames(dataset, count: int):
    """The first ``count`` images of ``dataset`` as (1, 3, H, W) uint8 tensors."""
    for i in range(min(count, len(dataset))):
        yield dataset[i][0][None]


def compare(session, network, images, priors) -> dict:
    """Parity of every rule on ``images``: pixels, differing, beyond the bound; log p gap."""
    totals: dict[str, list[int]] = {}
    log_gap = 0.0
    for image in images:
        with torch.no_grad():
            probs = network(image).softmax(1)
        pixel_priors = resize_priors(priors, tuple(image.shape[-2:]))
        for name, (cost, pi) in rules(pixel_priors).items():
            labels, _, graph_probs = run_graph(session, image, cost, pi, probabilities=True)
            result = parity(probs, graph_probs, labels, cost, pi)
            own = parity(graph_probs, graph_probs, labels, cost, pi)  # float32 decision only
            sums = totals.setdefault(name, [0, 0, 0, 0])
            counts = (result.pixels, result.differing, result.outside, own.differing)
            for k, value in enumerate(counts):
                sums[k] += value
        gap = (graph_probs.clamp_min(1e-30).log() - probs.clamp_min(1e-30).log()).abs().max()
        log_gap = max(log_gap, gap.item())
    return {"rules": totals, "largest log p difference": log_gap}


def seconds(run, repeats: int) -> float:
    run()  # warm-up
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        run()
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def speed(session, network, image: torch.Tensor, repeats: int) -> dict:
    """Seconds per frame of onnxruntime and of PyTorch eager, network and one rule."""
    cost = load_cost(SPEED_RULE)

    def eager() -> None:
        with torch.inference_mode():
            decide(network(image).softmax(1), cost)

    def graph() -> None:
        run_graph(session, image, cost)

    h, w = image.shape[-2:]
    return {
        "size": [int(h), int(w)],
        "onnxruntime s": seconds(graph, repeats),
        "pytorch s": seconds(eager, repeats),
        "bytes labels + margin": int(h * w * 5),
        "bytes labels": int(h * w),
        "bytes probabilities float32": int(19 * h * w * 4),
    }


def table(results: dict) -> str:
    lines = [
        "| images | rule | pixels | differing | beyond the bound | differing on the graph's "
        "probabilities |",
        "|---|---|---:|---:|---:|---:|",
    ]
    for where, result in results.items():
        for name, counts in result["parity"]["rules"].items():
            lines.append(f"| {where} | {name} | " + " | ".join(map(str, counts)) + " |")
    lines += [
        "",
        "| images | largest Δ log p | onnxruntime s/frame | PyTorch s/frame | ratio | "
        "labels + margin B/frame | probabilities B/frame |",
        "|---|---:|---:|---:|---:|---:|---:|",
    ]
    for where, result in results.items():
        s = result["speed"]
        ratio = s["onnxruntime s"] / s["pytorch s"]
        lines.append(
            f"| {where} | {result['parity']['largest log p difference']:.2e} | "
            f"{s['onnxruntime s']:.3f} | {s['pytorch s']:.3f} | {ratio:.2f} | "
            f"{s['bytes labels + margin']:,} | {s['bytes probabilities float32']:,} |"
        )
    return "\n".join(lines)


def main(args: Sequence[str] | None = None) -> None:
    args = parse_options(ExportBenchOptions, args, "bench_export.py", __doc__.splitlines()[0])
    with user_errors():
        plan = plan_export(ExportOptions(
            ckpt_path=[args.ckpt_path] if args.ckpt_path else None,
            output=str(args.output_dir / "model.onnx"), probabilities=True, overwrite=True,
        ))  # fmt: skip
        session = onnx_session(export(plan).graph)
        checkpoint = load_costseg_checkpoint(find_checkpoint(plan.ckpt_path))
        network, priors = checkpoint.network.eval(), checkpoint.priors
        sets = {
            "toy validation": build_dataset(checkpoint.data_config, "val"),
            "Cityscapes-layout": build_dataset(checkpoint.data_config, "val", args.cityscapes),
        }
        counts = {"toy validation": args.toy_images, "Cityscapes-layout": args.frames}
        results = {}
        for where, dataset in sets.items():
            images = list(frames(dataset, counts[where]))
            size = "x".join(str(s) for s in images[0].shape[-2:])
            results[f"{where} {size} ({len(images)})"] = {
                "parity": compare(session, network, images, priors),
                "speed": speed(session, network, images[0], args.repeats),
            }
        text = table(results)
        (args.output_dir / "bench.json").write_text(json.dumps(results, indent=2))
        print(text)


if __name__ == "__main__":
    main()
