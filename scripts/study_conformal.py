"""The conformal study of docs/results.md: prediction sets anchored on a cost rule, sized by
conformal risk control (docs/definitions.md §18).

    python scripts/study_conformal.py --ckpt_path A.ckpt [--output_dir study_conformal]

The network runs once per image of the checkpoint's data, split --split (its raw probabilities,
no scaling). Each of the robotistic, altruistic and egoistic rules anchors the sets (its decision
is in every set), LAC and APS; every image's loss is kept on the grid λ = 0, 1/STEPS, ..., 1,
with uniform weights and cost-weighted ones (the rule's own matrix, w_j = the mean cost of
missing class j; the robotistic matrix, 1 − I, weighs every class alike, so its cost-weighted
rows would repeat the uniform ones and are left out), together with the set sizes, the singleton
sets and the coverage of person pixels in the street RoI (RoI 1) at every λ.

Then, for each α of --alpha, over --splits random halves (calibration / test, drawn with --seed;
the same halves for every row): λ̂ from the calibration half, and on the test half the mean loss
(the empirical risk, next to α), the mean set size per labelled pixel, the share of singleton
sets and the person coverage in the street RoI, all pooled over the half's pixels. The table
gives their means over the splits, and "reached" the share of splits in which some λ met the
bound (else λ̂ = 1: every class). Writes ``study.md`` and ``study.json`` in --output_dir.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Literal

import numpy as np
import torch

from costseg.calibration.conformal import (
    KINDS,
    class_weights,
    conformity_scores,
    crc_threshold,
    lambda_grid,
    set_losses,
    set_size_curves,
)
from costseg.classes import CLASS_NAMES, IGNORE_INDEX
from costseg.cli import parse_options, user_errors
from costseg.data.from_config import build_dataset
from costseg.data.prior_maps import PriorMaps
from costseg.networks.ensemble import open_sources
from costseg.networks.protocols import Protocol
from costseg.networks.sources import batches, resolve_device
from costseg.options import NetworkOptions, SourceOptions, option, same_option
from costseg.rules import apply_rules, parse_rules
from costseg.values import fraction, whole_number

RULES = ("robotistic", "altruistic", "egoistic")
PERSON = CLASS_NAMES.index("person")
STREET = 1


@dataclass
class StudyOptions:
    """What the study can be told (``--help``)."""

    ckpt_path: str | None = option(
        help="the network (a costseg checkpoint)", required=True, metavar="PATH"
    )
    output_dir: Path = option(Path("study_conformal"), "a new folder for the study", type=Path)
    split: Literal["train", "val", "test"] = same_option(SourceOptions, "split", help="the images")
    alpha: list[float] = option([0.1, 0.05, 0.01], "the risk levels α", type=fraction)
    splits: int = option(100, "calibration / test halves", type=whole_number(1))
    steps: int = option(1000, "the λ grid: 0, 1/STEPS, ..., 1", type=whole_number(1))
    seed: int = option(0, "seed of the halves", type=whole_number(0))
    batch_size: int = same_option(SourceOptions, "batch_size", 8)
    device: str = same_option(NetworkOptions, "device")


def parse_args(args: Sequence[str] | None = None) -> StudyOptions:
    """The study's options; ValueError for a folder that exists or a checkpoint that does not."""
    opts = parse_options(StudyOptions, args, "study_conformal.py", __doc__.split("\n\n")[0])
    if opts.output_dir.exists():
        raise ValueError(f"{opts.output_dir} exists: choose another --output_dir")
    if not Path(opts.ckpt_path).is_file():
        raise ValueError(f"checkpoint not found: {opts.ckpt_path}")
    return opts


def collect(args: StudyOptions, grid: torch.Tensor) -> tuple[dict, dict, set]:
    """One pass of the network: per (rule, set) the per-image curves on ``grid`` (numpy); per
    rule its own person recall in the street RoI (the set {d(x)}); the rules whose matrix
    weighs every class alike."""
    device = resolve_device(args.device)
    source = open_sources(args.ckpt_path, None, None, device, Protocol(), None, 0)
    if source.priors is None or source.data_config is None:
        raise ValueError(f"{args.ckpt_path} has no priors or data: the street RoI needs them")
    dataset = build_dataset(source.data_config, args.split)
    rules = parse_rules(RULES)
    weights = {r.name: class_weights(r.cost) for r in rules}
    maps = PriorMaps(source.priors, CLASS_NAMES, device)
    parts: dict[tuple[str, str], dict[str, list]] = {}
    recall = {r.name: [0, 0] for r in rules}
    with torch.inference_mode():
        for batch in batches(source, dataset, range(len(dataset)), args.batch_size, device):
            labels, roi = batch.labels, maps.at(tuple(batch.labels.shape[-2:]))[1]
            person = (labels == PERSON) & (roi == STREET)
            probs = source.probabilities_of(batch.scores)
            decisions = apply_rules(probs, rules)
            for k, rule in enumerate(rules):
                recall[rule.name][0] += int((person & (decisions[:, k] == PERSON)).sum())
                recall[rule.name][1] += int(person.sum())
                for kind in KINDS:
                    scores = conformity_scores(probs, decisions[:, k], kind)
                    curves = image_curves(scores, labels, person, grid, rule.cost)
                    for key, value in curves.items():
                        parts.setdefault((rule.name, kind), {}).setdefault(key, []).append(value)
    curves = {key: {k: np.concatenate(v) for k, v in c.items()} for key, c in parts.items()}
    alike = {name for name, w in weights.items() if bool((w == w[0]).all())}
    return curves, {name: hit / total for name, (hit, total) in recall.items()}, alike


def image_curves(scores, labels, person, grid, cost) -> dict[str, np.ndarray]:
    """Per image of one batch: the losses (uniform, and weighted by the rule's matrix
    ``cost``: evaluate.py's --conformal_loss) and the set statistics on ``grid``; person pixels
    of the street RoI and their missed share."""
    sizes = set_size_curves(scores, grid, labels != IGNORE_INDEX)
    found = {
        "uniform": set_losses(scores, labels, grid),
        "cost": set_losses(scores, labels, grid, "cost", cost),
        "person_missed": set_losses(scores, labels, grid, mask=person).nan_to_num(0),
        "person_pixels": person.flatten(1).sum(1),
        "pixels": sizes.pixels,
        "sizes": sizes.sizes,
        "singletons": sizes.singletons,
    }
    return {k: v.double().cpu().numpy() for k, v in found.items()}


def over_splits(c: dict, losses: np.ndarray, halves: list, grid: np.ndarray, alpha: float):
    """Means over the halves of λ̂, the test loss, the set size, the singleton share, the person
    coverage, and the share of halves in which the bound was reached."""
    rows = []
    for cal, test in halves:
        control = crc_threshold(losses[cal], grid, alpha)
        i, pixels = control.index, c["pixels"][test].sum()
        person = c["person_pixels"][test]
        missed = (c["person_missed"][test, i] * person).sum()
        rows.append([
            control.lam, np.nanmean(losses[test, i]), c["sizes"][test, i].sum() / pixels,
            c["singletons"][test, i].sum() / pixels, 1 - missed / person.sum(), control.reached,
        ])  # fmt: skip
    keys = ("lambda_hat", "test_loss", "set_size", "singletons", "person_coverage", "reached")
    return dict(zip(keys, np.mean(rows, axis=0).tolist(), strict=True))


def table(results: list[dict], recall: dict[str, float], n: int) -> str:
    """The study's Markdown table, and the rules' own person recall."""
    lines = [
        f"Means over the splits ({n} calibration images each). Person recall of the rule alone "
        "in the street RoI: "
        + ", ".join(f"{name} {100 * value:.1f} %" for name, value in recall.items())
        + ".",
        "",
        "| rule | set | loss | α | λ̂ | test loss | reached | set size | singletons | person "
        "coverage, street |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in results:
        lines.append(
            f"| {r['rule']} | {r['set'].upper()} | {r['loss']} | {r['alpha']:g} | "
            f"{r['lambda_hat']:.3f} | {r['test_loss']:.4f} | {100 * r['reached']:.0f} % | "
            f"{r['set_size']:.2f} | {100 * r['singletons']:.1f} % | "
            f"{100 * r['person_coverage']:.1f} % |"
        )
    return "\n".join(lines) + "\n"


def main(args: Sequence[str] | None = None) -> None:
    args = parse_args(args)
    grid = lambda_grid(args.steps)
    curves, recall, alike = collect(args, grid)
    images = len(next(iter(curves.values()))["pixels"])
    rng = np.random.default_rng(args.seed)
    halves = [np.split(rng.permutation(images), [images // 2]) for _ in range(args.splits)]
    results = []
    for (rule, kind), c in curves.items():
        for loss in ("uniform",) if rule in alike else ("uniform", "cost"):
            for alpha in args.alpha:
                stats = over_splits(c, c[loss], halves, grid.numpy(), alpha)
                results.append({"rule": rule, "set": kind, "loss": loss, "alpha": alpha, **stats})
    text = table(results, recall, images // 2)
    args.output_dir.mkdir(parents=True)
    (args.output_dir / "study.md").write_text(text)
    settings = {k: str(v) if isinstance(v, Path) else v for k, v in asdict(args).items()}
    summary = {"settings": settings, "images": images, "person_recall": recall, "rows": results}
    (args.output_dir / "study.json").write_text(json.dumps(summary, indent=2))
    print(text)


if __name__ == "__main__":
    with user_errors():
        main()
