"""The design study of docs/results.md: value systems designed from several requirements and
certified by Pareto Testing (docs/definitions.md §20), over many random splits.

    python scripts/study_design.py --ckpt_path A.ckpt [--output_dir study_design]

The network runs once per image of the checkpoint's data: the --pool split (the calibration
images that each split divides into D1 and D2) and the --test split (fresh images: the realised
risks). For each requirement set (--requirements, several constraints each) and each search space
a fixed pool of candidate matrices is scored on every image once (the fused count pass, every
pixel): the triangle and Lagrangian grids of --budget points, and for the aggregate space the
candidates of one NSGA-II search (--budget, --seed) on the first --search_images images of the
--search split (disjoint from both). Then over --splits random halves of the pool (D1 / D2, drawn
with --seed, the same for every space): Pareto Testing at δ (--delta) chooses a matrix by the
objective (the share of pixels that agree with argmax) or certifies nothing. The table gives,
per requirement set and space, the share of splits with a certified matrix, each constraint's
violation rate (the chosen matrix's risk on the test images above α, over the splits that chose
one; Learn-then-Test guarantees at most δ jointly), and the chosen matrix's objective on the test
images next to that of the best certified triangle point of the same split. Writes ``study.md``
and ``study.json`` in --output_dir.
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch

from costseg.calibration.design_search import search
from costseg.calibration.guarantee import defined_risks
from costseg.calibration.pareto_testing import choose, pareto_testing
from costseg.classes import CLASS_NAMES
from costseg.cli import parse_options, user_errors
from costseg.data.from_config import build_dataset
from costseg.data.prior_maps import PriorMaps
from costseg.decision import count_decisions, prepare_counts
from costseg.evaluation.analyses.design import SearchImages, image_losses, pixel_seeds, spaces
from costseg.evaluation.settings import DesignSettings, design_settings
from costseg.metrics.requirements import Requirements
from costseg.networks.ensemble import open_sources
from costseg.networks.protocols import Protocol
from costseg.networks.sources import batches, resolve_device
from costseg.options import EvalOptions, option, same_option, whole_number

REQUIREMENTS = (
    "person:roi1:recall>=0.75 building:roi3:precision>=0.65",
    "person:roi1:recall>=0.85 building:roi3:precision>=0.85",
    "person:roi1:recall>=0.99 building:roi3:precision>=0.99",
)
"""Requirement sets of the demo model: one the triangle meets, one only the other spaces meet,
one no space can certify at δ = 0.1 with 50 certification images."""
SPACES = ("triangle", "lagrangian", "aggregate")


@dataclass
class StudyOptions:
    """Everything ``scripts/study_design.py`` can be told."""

    ckpt_path: list[str] | None = same_option(EvalOptions, "ckpt_path", required=True)
    output_dir: str = option("study_design", "the study's folder")
    requirements: list[str] = option(
        list(REQUIREMENTS), "requirement sets, each its constraints separated by spaces"
    )
    pool: str = option("test", "the split D1 and D2 are drawn from")
    test: str = option("val", "the split of the realised risks")
    search: str = option("train", "the split the aggregate search sees")
    search_images: int = option(50, "images of --search the aggregate search sees",
                                type=whole_number(1))  # fmt: skip
    budget: int = same_option(EvalOptions, "design_budget", 100)
    delta: float = same_option(EvalOptions, "design_delta", 0.1)
    splits: int = option(100, "random D1 / D2 splits of the pool", type=whole_number(1))
    seed: int = same_option(EvalOptions, "seed")
    device: str = same_option(EvalOptions, "device")
    batch_size: int = same_option(EvalOptions, "batch_size", 8)


def probabilities(source, config, split: str, count: int | None, device, batch_size: int):
    """Every image's (probs, labels, roi) of ``split`` (its first ``count``), as a list of
    batches on the CPU."""
    dataset = build_dataset(config, split)
    indices = list(range(len(dataset) if count is None else min(count, len(dataset))))
    priors = PriorMaps(source.priors, CLASS_NAMES, device)
    out = []
    with torch.inference_mode():
        for batch in batches(source, dataset, indices, batch_size, device, 0, f"{split} images"):
            _, roi = priors.at(tuple(batch.labels.shape[-2:]))
            probs = source.probabilities_of(batch.scores).float().cpu()
            out.append((probs, batch.labels.cpu(), roi.expand_as(batch.labels).cpu()))
    return out


def scored(pool, matrices: torch.Tensor, req: Requirements):
    """Per image and candidate: the (n, L, K) losses and the (n, L) agreements; (n,) labelled
    pixels."""
    losses, agree = [], []
    prepared = [prepare_counts(p, y, r) for p, y, r in pool]
    for matrix in matrices:
        mine, ours = [], []
        for inputs in prepared:
            counts = count_decisions(inputs, matrix)
            mine.append(image_losses(req, counts, matrix))
            ours.append(counts.agree)
        losses.append(torch.cat(mine).numpy())
        agree.append(torch.cat(ours).numpy())
    labelled = torch.cat([(y != 255).flatten(1).sum(1) for _, y, _ in pool]).numpy()
    return np.stack(losses, 1), np.stack(agree, 1).astype(float), labelled.astype(float)


def aggregate_pool(
    settings: DesignSettings, req: Requirements, search_images, seed: int, budget: int
) -> torch.Tensor:
    """The candidates of one NSGA-II search of the aggregate space on ``search_images``,
    scored as ``evaluate.py --design`` scores them (every pixel that can change a constraint,
    and a share of each image's pixels, drawn with its own seed, for the objective)."""
    found, first = SearchImages(), 0
    space = next(s for s in spaces(settings, req) if s.name == "aggregate")
    for p, y, r in search_images:
        seeds = pixel_seeds(seed, list(range(first, first + len(y))))
        found.add_pixels(p, y, r, settings.pixels, req, [space.hull()], seeds)
        first += len(y)
    return search(space, found.scorer(req, lambda losses: None), req.alphas, budget, seed).matrices


def main(args: Sequence[str] | None = None) -> None:
    args = parse_options(StudyOptions, args, "study_design.py", __doc__.split("\n\n")[0])
    start = time.perf_counter()
    device = resolve_device(args.device)
    source = open_sources(args.ckpt_path, None, None, device, Protocol(), None, 0)
    config = source.data_config
    pool = probabilities(source, config, args.pool, None, device, args.batch_size)
    test = probabilities(source, config, args.test, None, device, args.batch_size)
    seen = probabilities(source, config, args.search, args.search_images, device, args.batch_size)
    n = sum(len(y) for _, y, _ in pool)
    rng = np.random.default_rng(args.seed)
    halves = [rng.permutation(n) for _ in range(args.splits)]
    rows, record = [], {"args": asdict(args), "sets": []}
    for text in args.requirements:
        req = Requirements.parse(text.split())
        alphas = np.array(req.alphas)
        found = {}
        for name in SPACES:
            settings = design_settings(  # as evaluate.py --design resolves them
                EvalOptions(design=name, require=list(req.texts), design_delta=args.delta,
                            design_budget=args.budget, seed=args.seed)
            )  # fmt: skip
            if name == "aggregate":
                matrices = aggregate_pool(settings, req, seen, args.seed, args.budget)
            else:
                space = spaces(settings, req)[0]
                matrices = torch.stack([space.matrix(p) for p in space.grid()])
            losses, agree, labelled = scored(pool, matrices, req)
            t_losses, t_agree, t_labelled = scored(test, matrices, req)
            test_risk = defined_risks(t_losses)[0]  # (L, K)
            test_objective = t_agree.sum(0) / t_labelled.sum()
            chosen = []
            for order in halves:
                d1, d2 = order[: n // 2], order[n // 2 :]
                objective_d1 = agree[d1].sum(0) / labelled[d1].sum()
                result = pareto_testing(losses[d1], losses[d2], alphas, args.delta,
                                        objective_d1)  # fmt: skip
                objective_all = agree.sum(0) / labelled.sum()
                chosen.append(choose(result, objective_all))
            found[name] = (chosen, test_risk, test_objective, len(matrices))
        triangle_objective = [
            math.nan if k is None else float(found["triangle"][2][k]) for k in found["triangle"][0]
        ]
        summary = {"requirements": list(req.texts), "alphas": req.alphas, "spaces": {}}
        for name, (chosen, test_risk, test_objective, size) in found.items():
            picked = [k for k in chosen if k is not None]
            violations = [float(np.mean([test_risk[k, i] > alphas[i] for k in picked]))
                          if picked else math.nan for i in range(len(alphas))]  # fmt: skip
            any_violation = (float(np.mean([(test_risk[k] > alphas).any() for k in picked]))
                             if picked else math.nan)  # fmt: skip
            mine = [float(test_objective[k]) for k in picked]
            beside = [t for k, t in zip(chosen, triangle_objective, strict=True)
                      if k is not None and not math.isnan(t)]  # fmt: skip
            entry = {
                "candidates": size,
                "certified_share": len(picked) / len(chosen),
                "violation_rates": violations,
                "any_violation_rate": any_violation,
                "test_objective": float(np.mean(mine)) if mine else math.nan,
                "triangle_test_objective": float(np.mean(beside)) if beside else math.nan,
                "splits_with_both": sum(
                    k is not None and not math.isnan(t)
                    for k, t in zip(chosen, triangle_objective, strict=True)
                ),
            }
            summary["spaces"][name] = entry
            rows.append((text, name, entry))
        record["sets"].append(summary)
        print(f"{text}: done ({time.perf_counter() - start:.0f} s)")
    record["seconds"] = time.perf_counter() - start
    out = Path(args.output_dir)
    out.mkdir(parents=True, exist_ok=True)
    (out / "study.json").write_text(json.dumps(record, indent=1))
    (out / "study.md").write_text(table(rows, args))
    print(table(rows, args))


def table(rows, args) -> str:
    """The study's Markdown table."""
    lines = [
        f"| requirements | space | candidates | certified ({args.splits} splits) | violation "
        f"rate per constraint (δ = {args.delta}) | any violated | test agreement | best "
        "certified triangle point, same splits |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for text, name, e in rows:
        rates = ", ".join("–" if math.isnan(v) else f"{v:.2f}" for v in e["violation_rates"])
        any_rate = "–" if math.isnan(e["any_violation_rate"]) else f"{e['any_violation_rate']:.2f}"
        mine = "–" if math.isnan(e["test_objective"]) else f"{e['test_objective']:.4f}"
        tri = e["triangle_test_objective"]
        tri = "–" if math.isnan(tri) else f"{tri:.4f} ({e['splits_with_both']} splits)"
        lines.append(f"| {text} | {name} | {e['candidates']} | {e['certified_share']:.2f} | "
                     f"{rates} | {any_rate} | {mine} | {tri} |")  # fmt: skip
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    with user_errors():
        main()
