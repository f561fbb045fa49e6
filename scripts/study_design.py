"""The design study of docs/results.md: value systems designed from several requirements and
certified by Pareto Testing (docs/definitions.md §20, §21), over many random splits.

    python scripts/study_design.py --ckpt_path A.ckpt [--output_dir study_design]

The network runs once per image of the checkpoint's data: the --pool split (the calibration
images that each split divides into D1 and D2), the --test split (fresh images: the realised
risks) and --search_images images of the --search split from index --search_from (fresh
images, disjoint from both: by default val's images after the test images). For
each requirement set (--requirements, several constraints each) and each search space of
:data:`SPACES`, a fixed pool of candidate matrices is made without the pool's images: a grid
space's every point within --budget, a searched space's --budget candidates of one search on the
--search images (seeded by --seed, scored as ``evaluate.py --design`` scores D1). Every candidate
is scored on every pixel of every pool image (the fused count pass), the chosen ones on the test
images too. Over --splits
random halves of the pool (split s is the one ``evaluate.py --design --seed s`` draws), Pareto
Testing at δ (--delta) chooses a matrix by the objective (the share of pixels that agree with
argmax, on the whole pool) or certifies nothing. Per requirement set and space: the share of
splits with a certified matrix; each constraint's violation rate (the chosen matrix's risk on
the test images above α, over the splits that chose one; Pareto Testing bounds the probability
that any is violated by δ); the chosen matrix's agreement on the test images; the seconds the
space took. Writes ``study.md`` and ``study.json`` in --output_dir.
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
from costseg.calibration.pareto_testing import choose, pareto_testing, split_images
from costseg.classes import CLASS_NAMES
from costseg.cli import parse_options, user_errors
from costseg.data.from_config import build_dataset
from costseg.data.prior_maps import PriorMaps
from costseg.decision import count_decisions, prepare_counts
from costseg.evaluation.analyses.design import SearchImages, continuous, spaces
from costseg.evaluation.settings import DesignSettings, design_settings
from costseg.metrics.requirements import Requirements
from costseg.networks.ensemble import open_sources
from costseg.networks.protocols import Protocol
from costseg.networks.sources import batches, resolve_device
from costseg.options import EvalOptions, option, same_option, whole_number
from costseg.report.outputs import claim_output_dir, mark_complete

REQUIREMENTS = (
    # one matrix for the whole image can meet these
    "person:roi1:recall>=0.75 building:roi3:precision>=0.65",
    "car:roi0:recall>=0.9 building:roi0:precision>=0.85",
    "person:roi1:recall>=0.85 building:roi3:precision>=0.85",
    "person:roi1:recall>=0.7 car:roi1:recall>=0.85 building:roi3:precision>=0.8",
    "person:roi1:recall>=0.7 car:roi1:recall>=0.85 building:roi3:precision>=0.8 "
    "bicycle:roi1:recall>=0.4",
    # a recall in the street and a precision elsewhere: one matrix trades them off
    "person:roi1:recall>=0.8 person:roi2:precision>=0.35",
    "rider:roi1:recall>=0.7 rider:roi3:precision>=0.4",
    "car:roi1:recall>=0.95 car:roi2:precision>=0.5",
    "person:roi1:recall>=0.7 car:roi1:recall>=0.85 person:roi3:precision>=0.35",
    "person:roi1:recall>=0.7 car:roi1:recall>=0.85 person:roi2:precision>=0.35 "
    "person:roi3:precision>=0.35",
    # beyond what 50 certification images can show, or contradictory
    "person:roi1:recall>=0.99 building:roi3:precision>=0.99",
    "person:roi1:recall>=0.95 person:roi1:precision>=0.9",
    "rider:roi0:recall>=0.9 rider:roi0:precision>=0.8 bicycle:roi2:recall>=0.9",
)
"""Requirement sets of the demo model, 2 to 4 constraints over person, rider, car, bicycle and
building in RoIs 0 to 3, chosen from the argmax risks of its test images."""

SPACES: dict[str, tuple[str, str | None]] = {
    "triangle": ("triangle", None),
    "lagrangian grid": ("lagrangian", "grid"),
    "lagrangian search": ("lagrangian", "continuous"),
    "regional": ("regional", "continuous"),
    "aggregate": ("aggregate", None),
}
"""Each space of the study: its ``--design`` and ``--design_search``."""


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
    search: str = option("val", "the split the searched spaces see")
    search_images: int = option(50, "images of --search the searched spaces see",
                                type=whole_number(1))  # fmt: skip
    search_from: int = option(
        100,
        "the first --search image's index (the toy scenes draw any index of a split: val "
        "images 100 on are fresh)",
        type=whole_number(0),
    )
    budget: int = same_option(EvalOptions, "design_budget", 100)
    delta: float = same_option(EvalOptions, "design_delta", 0.1)
    splits: int = option(100, "random D1 / D2 splits of the pool", type=whole_number(1))
    seed: int = same_option(EvalOptions, "seed")
    device: str = same_option(EvalOptions, "device")
    batch_size: int = same_option(EvalOptions, "batch_size", 8)


def probabilities(
    source, config, split: str, images: range | None, device, batch_size: int, root=None
):
    """Every image's (probs, labels, roi) of ``split`` (or its ``images``; of the Cityscapes
    tree ``root`` instead of the configured data), as a list of batches on the CPU."""
    if images is not None and f"{split}_length" in config["init_args"]:  # the toy scenes
        config = {**config, "init_args": {**config["init_args"], f"{split}_length": images.stop}}
    dataset = build_dataset(config, split, root)
    indices = list(range(len(dataset)) if images is None else images)
    if indices and indices[-1] >= len(dataset):
        raise ValueError(f"the {split} split holds {len(dataset)} images, not the "
                         f"{indices[-1] + 1} asked for")  # fmt: skip
    priors = PriorMaps(source.priors, CLASS_NAMES, device)
    out = []
    with torch.inference_mode():
        for batch in batches(source, dataset, indices, batch_size, device, 0, f"{split} images"):
            _, roi = priors.at(tuple(batch.labels.shape[-2:]))
            probs = source.probabilities_of(batch.scores).float().cpu()
            out.append((probs, batch.labels.cpu(), roi.expand_as(batch.labels).cpu()))
    return out


class Counted:
    """Every candidate's per-image decision counts on a list of prepared batches: (n, L, R + 1,
    N, N + 1) confusions and (n, L) agreements with argmax, every pixel."""

    def __init__(self, prepared: list, matrices: torch.Tensor) -> None:
        confusion, agree = [], []
        for matrix in matrices:
            counts = [count_decisions(inputs, matrix) for inputs in prepared]
            confusion.append(torch.cat([c.confusion for c in counts]).int())
            agree.append(torch.cat([c.agree for c in counts]))
        self.confusion = torch.stack(confusion, 1)
        self.agree = torch.stack(agree, 1).numpy().astype(float)

    def losses(self, req: Requirements) -> np.ndarray:
        """(n, L, K) per-image constraint losses."""
        per_candidate = [
            req.losses(self.confusion[:, j].long()) for j in range(self.confusion.shape[1])
        ]
        return torch.stack(per_candidate, 1).numpy()


def candidates(settings: DesignSettings, req: Requirements, seen: list, seed: int) -> torch.Tensor:
    """The space's candidate matrices: a grid's points, or one search's candidates on the
    ``seen`` images, scored as ``evaluate.py --design`` scores D1 (every pixel that can change a
    constraint, and a share of each image's pixels, drawn with its own seed, for the
    objective)."""
    space = spaces(settings, req)[0]
    searched = continuous(space, settings) or settings.space == "aggregate"
    if not searched:
        return torch.stack([space.matrix(p) for p in space.grid()])
    found = SearchImages.of_images(seen, settings.pixels, req, [space.hull()], seed)
    score = found.scorer(req, lambda losses: None)
    return search(space, score, req.alphas, settings.budget, seed, req.maximize,
                  continuous=searched, delta=settings.delta).matrices  # fmt: skip


def certify(
    matrices: torch.Tensor, pool: Counted, test: list, req: Requirements, splits: list, delta: float
) -> dict:
    """Pareto Testing on each split of the ``pool``; the chosen matrices' risks and agreement on
    the ``test`` images (prepared batches)."""
    alphas = np.array(req.alphas)
    losses = pool.losses(req)
    labelled = pool.confusion[:, 0, 0].sum((-1, -2)).numpy().astype(float)
    objective_all = pool.agree.sum(0) / labelled.sum()
    chosen = []
    for d1, d2 in splits:
        objective_d1 = pool.agree[d1].sum(0) / labelled[d1].sum()
        result = pareto_testing(losses[d1], losses[d2], alphas, delta, objective_d1)
        chosen.append(choose(result, objective_all))
    picked = [k for k in chosen if k is not None]
    if not picked:
        return {"candidates": len(matrices), "certified_share": 0.0,
                "violation_rates": [math.nan] * len(alphas), "any_violation_rate": math.nan,
                "test_agreement": math.nan}  # fmt: skip
    distinct = sorted(set(picked))  # the test images measure only the chosen matrices
    measured = Counted(test, matrices[distinct])
    at = {k: j for j, k in enumerate(distinct)}
    test_risk = defined_risks(measured.losses(req))[0][[at[k] for k in picked]]  # (chosen, K)
    test_labelled = measured.confusion[:, 0, 0].sum((-1, -2)).sum().item()
    agreement = measured.agree.sum(0)[[at[k] for k in picked]] / test_labelled
    above = test_risk > alphas
    return {
        "candidates": len(matrices),
        "certified_share": len(picked) / len(chosen),
        "chosen": picked,
        "violation_rates": above.mean(0).tolist(),
        "any_violation_rate": float(above.any(1).mean()),
        "test_agreement": float(agreement.mean()),
    }


def main(args: Sequence[str] | None = None) -> None:
    args = parse_options(StudyOptions, args, "study_design.py", __doc__.split("\n\n")[0])
    battery = [Requirements.parse(text.split()) for text in args.requirements]
    out = claim_output_dir(args.output_dir, False, Path(args.output_dir))
    start = time.perf_counter()
    device = resolve_device(args.device)
    source = open_sources(args.ckpt_path, None, None, device, Protocol(), None, 0)
    config = source.data_config
    seen = range(args.search_from, args.search_from + args.search_images)
    read = {name: probabilities(source, config, split, count, device, args.batch_size)
            for name, split, count in [("pool", args.pool, None), ("test", args.test, None),
                                       ("seen", args.search, seen)]}  # fmt: skip
    pool = [prepare_counts(*batch) for batch in read["pool"]]
    test = [prepare_counts(*batch) for batch in read["test"]]
    n = sum(len(y) for _, y, _ in read["pool"])
    splits = [split_images(n, args.seed + s) for s in range(args.splits)]
    images = {"pool": n, "test": sum(len(y) for _, y, _ in read["test"])}
    record = {"args": asdict(args), "images": images, "sets": []}
    fixed: dict[str, tuple] = {}  # the triangle's pool counts: its grid serves every set
    for text, req in zip(args.requirements, battery, strict=True):
        summary = {"requirements": list(req.texts), "alphas": req.alphas, "spaces": {}}
        for name, (space, how) in SPACES.items():
            began = time.perf_counter()
            settings = design_settings(  # as evaluate.py --design resolves them
                EvalOptions(design=space, design_search=how, require=list(req.texts),
                            design_delta=args.delta, design_budget=args.budget, seed=args.seed)
            )  # fmt: skip
            if name in fixed:
                matrices, counted = fixed[name]
            else:
                matrices = candidates(settings, req, read["seen"], args.seed)
                counted = Counted(pool, matrices)
                if space == "triangle":
                    fixed[name] = matrices, counted
            entry = certify(matrices, counted, test, req, splits, args.delta)
            entry["seconds"] = time.perf_counter() - began
            summary["spaces"][name] = entry
        record["sets"].append(summary)
        print(f"{text}: done ({time.perf_counter() - start:.0f} s)", flush=True)
    record["seconds"] = time.perf_counter() - start
    (out / "study.json").write_text(json.dumps(record, indent=1))
    (out / "study.md").write_text(tables(record, args))
    mark_complete(out)
    print(tables(record, args))


def tables(record: dict, args) -> str:
    """The study's Markdown tables: the share of splits certified, the chosen matrices' test
    agreement, their violation rates per constraint."""

    def number(value: float, digits: int) -> str:
        return "–" if math.isnan(value) else f"{value:.{digits}f}"

    cells = {
        f"certified ({args.splits} splits)": lambda e: number(e["certified_share"], 2),
        "agreement with argmax on the test images": lambda e: number(e["test_agreement"], 4),
        f"violation rate per constraint on the test images (δ = {args.delta})": lambda e: ", ".join(
            number(v, 2) for v in e["violation_rates"]
        ),
    }
    text = []
    for title, cell in cells.items():
        text += [f"**{title}**", "", "| requirements | " + " | ".join(SPACES) + " |",
                 "|---" * (len(SPACES) + 1) + "|"]  # fmt: skip
        for s in record["sets"]:
            row = [cell(s["spaces"][name]) for name in SPACES]
            text.append(f"| {' '.join(s['requirements'])} | " + " | ".join(row) + " |")
        text.append("")
    seconds = {name: sum(s["spaces"][name]["seconds"] for s in record["sets"]) for name in SPACES}
    text.append("Seconds per space, all sets (search and scoring): "
                + ", ".join(f"{name} {t:.0f}" for name, t in seconds.items()) + ".")  # fmt: skip
    return "\n".join(text) + "\n"


if __name__ == "__main__":
    with user_errors():
        main()
