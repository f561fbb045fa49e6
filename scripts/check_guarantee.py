"""Empirical check of the Learn-then-Test guarantee on the procedural world (docs/definitions.md
§7).

    python scripts/check_guarantee.py [--ckpt_path PATH ...] [--n 50] [--trials 200] [--test 1000]
    python scripts/check_guarantee.py --defer_sweep 0 1 0.05 --cost robotistic egoistic \
        --target "person:roi1:handled_recall>=0.95" --maximize all:roi1:coverage

evaluate.py's options mean the same here (--sweep is the grid's step, --guarantee is δ; several
--ckpt_path / --network: their ensemble; --shift sees the test images, never the calibration
pool, through each corruption: the guarantee certified on clean images, tested under shift).
Fresh procedural scenes (split "test", --scene_seed 1000:
unrelated to training) form a pool: the first
--test images are the test set, the next ones the calibration pool (--trials × --n images by
default: disjoint, independent calibration sets). The network runs once per image; the per-image
counts of the target and of --maximize under every candidate λ (the grid points, or with
--defer_sweep every --cost rule at every defer cost, as ``evaluate.py --defer_sweep``) are kept in
``counts.npz`` in --output_dir (reruns are instant). Per calibration set, Learn-then-Test at δ
picks the certified λ with the best pooled --maximize (or nothing), and the naive rule
(``evaluate.py --target``) the λ meeting the target on the pooled calibration images with the
best --maximize (both: ties to the larger defer cost; fixed-sequence testing walks each rule's
defer costs from the smallest up, at δ / number of rules). The test risk of λ is its mean
per-image loss on the test set (images with an undefined loss left out, counted); a violation
is ``R_test(λ̂) > α``. Writes ``guarantee_check.json`` and ``guarantee_check.png``.
"""

# No ``from __future__ import annotations``: GuaranteeOptions's annotations are evaluated at once,
# so the dataclass also builds where the script is loaded by path, outside sys.modules (tests).
import argparse
import json
import math
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np
import torch
from matplotlib.figure import Figure
from torch.utils.data import DataLoader, Subset
from tqdm import tqdm

from costseg import workers
from costseg.calibration.guarantee import (
    Bound,
    learn_then_test_paths,
    minimum_images,
    tests_sharing_delta,
)
from costseg.checkpoints import find_checkpoint
from costseg.classes import CLASS_NAMES
from costseg.cli import build_parser as build_options_parser
from costseg.cli import user_errors
from costseg.data.prior_maps import PriorMaps
from costseg.data.priors import check_priors_file, read_priors_file
from costseg.data.shift import Shift, ShiftedDataset, parse_shift
from costseg.data.toy import StreetScenes
from costseg.evaluation.checks import check_selection, check_shifts
from costseg.metrics.per_image import per_image_counts, per_image_loss
from costseg.metrics.selection import (
    Metric,
    Target,
    best_points,
    meets,
    parse_metric,
    parse_target,
    risk_level,
)
from costseg.networks import load_costseg_checkpoint
from costseg.networks.ensemble import member_specs, open_sources
from costseg.networks.protocols import Protocol
from costseg.networks.sources import resolve_device
from costseg.options import EvalOptions, option, same_option, whole_number
from costseg.report.files import save_figure, write_json
from costseg.rules import RuleGroup, defer_costs, defer_group, grid_group, require_priors

RULES = {"ltt": "Learn-then-Test", "naive": "naive --target"}


@dataclass
class GuaranteeOptions:
    """The check's options: evaluate.py's where they mean the same (``--sweep`` is the grid's
    step, ``--guarantee`` is δ; ``--defer_sweep`` replaces the grid), with the check's defaults,
    then its own; the values derived from them last."""

    cost: list[str] = same_option(EvalOptions, "cost")
    ckpt_path: list[str] | None = same_option(EvalOptions, "ckpt_path")
    network: list[str] | None = same_option(EvalOptions, "network")
    seed: int = same_option(EvalOptions, "seed")
    priors: str | None = same_option(EvalOptions, "priors")
    output_dir: Path = same_option(
        EvalOptions, "output_dir", "runs/guarantee_check", help="the check's folder"
    )
    device: str = same_option(EvalOptions, "device")
    vertices: list[str] = same_option(EvalOptions, "vertices")
    vertex_scaling: Literal["none", "mean"] = same_option(EvalOptions, "vertex_scaling")
    batch_size: int = same_option(EvalOptions, "batch_size", 16)
    shift: list[str] = same_option(EvalOptions, "shift")
    sweep: float = same_option(EvalOptions, "sweep", 0.1)
    defer_sweep: list[float] | None = same_option(EvalOptions, "defer_sweep")
    target: list[str] = same_option(EvalOptions, "target", ["person:roi1:recall>=0.95"])
    maximize: str = same_option(EvalOptions, "maximize", "person:roi1:precision")
    guarantee: float = same_option(EvalOptions, "guarantee", 0.1)
    guarantee_method: Literal["bonferroni", "fixed_sequence"] = same_option(
        EvalOptions, "guarantee_method"
    )
    bound: Bound = option("hoeffding_bentkus", "the p-values' concentration bound")
    n: int = option(50, "images per calibration set", type=whole_number(1))
    trials: int = option(200, "calibration sets drawn", type=whole_number(1))
    test: int = option(1000, "images of the fresh test set", type=whole_number(1))
    cal_pool: int | None = option(
        help="default --trials × --n; smaller: sets overlap", type=whole_number(1)
    )
    scene_seed: int = option(1000, "scene seed (training uses 0)", type=whole_number(0))
    draw_seed: int = option(0, "seed of the calibration-set draws", type=whole_number(0))
    size: list[int] | None = option(
        help="default: the checkpoint's", type=whole_number(1), nargs=2, metavar=("H", "W")
    )
    target_spec: Target = field(init=False)
    max_spec: Metric = field(init=False)
    alpha: float = field(init=False)
    """The target's risk level α."""
    shifts: list[Shift] = field(init=False)

    def __post_init__(self) -> None:
        self.output_dir = Path(self.output_dir)
        self.target_spec = parse_target(self.target[0])  # one: check_selection refuses more
        self.max_spec = parse_metric(self.maximize)
        self.alpha = risk_level(self.target_spec)
        self.cal_pool = self.trials * self.n if self.cal_pool is None else self.cal_pool
        self.shifts = [parse_shift(text) for text in self.shift]


def build_parser() -> argparse.ArgumentParser:
    """The command line: the fields of :class:`GuaranteeOptions`."""
    return build_options_parser(GuaranteeOptions, "check_guarantee.py", __doc__.splitlines()[0])


def parse_args(argv: list[str] | None = None) -> GuaranteeOptions:
    """Parsed and checked options (evaluate.py's checks where they overlap); ValueError for a
    bad option."""
    args = GuaranteeOptions(**vars(build_parser().parse_args(argv)))
    resolve_device(args.device)
    check_selection(args, [candidates(args)])  # a bad --defer_sweep or --cost; α, δ in (0, 1)
    check_shifts(args.shift)
    check_priors_file(args.priors)
    if args.n > args.cal_pool:
        raise ValueError(f"need --n <= --cal_pool = {args.cal_pool}")
    return args


def candidates(args: GuaranteeOptions) -> RuleGroup:
    """The λ: the grid of --sweep over --vertices, or with --defer_sweep every --cost rule at
    every defer cost (one fixed-sequence path per rule)."""
    if args.defer_sweep is not None:
        return defer_group(args.cost, defer_costs(*args.defer_sweep))
    return grid_group(args.vertices, args.sweep, args.vertex_scaling)


def checkpoints(args: GuaranteeOptions) -> list[Path]:
    """The checkpoints in use: --ckpt_path (default the newest), or with --network alone the
    newest if there is one (for its priors, RoI map and image size)."""
    if args.network is None or args.ckpt_path is not None:
        return [find_checkpoint(p) for p, _ in member_specs(args.ckpt_path, None)]
    try:
        return [find_checkpoint(None)]
    except FileNotFoundError:
        return []


def load_source(args: GuaranteeOptions, paths: list[Path]) -> tuple[Any, Any, tuple[int, int]]:
    """(source, (priors, RoI map) or Nones, image size) of the checkpoints and --network: one
    network or their ensemble, as evaluate.py builds it."""
    device = resolve_device(args.device)
    ckpts = [str(p) for p in paths] if args.ckpt_path is not None else None
    source = open_sources(ckpts, args.network, None, device, Protocol(), None, 0)
    priors = source.priors
    config = (source.data_config or {}).get("init_args", {})
    if priors is None and paths:  # --network alone: the newest checkpoint's priors and size
        ckpt = load_costseg_checkpoint(paths[0])
        priors, config = ckpt.priors, (ckpt.data_config or {}).get("init_args", {})
    if args.priors is not None:
        priors = read_priors_file(args.priors, CLASS_NAMES)["priors"]
    size = tuple(args.size or config.get("size") or (128, 256))
    roi = None
    if priors is not None:
        priors, roi = PriorMaps(priors, CLASS_NAMES, device).at(size)
    if (args.target_spec.roi or args.max_spec.roi) and roi is None:
        raise ValueError("a RoI target or --maximize needs a checkpoint with priors (RoI map)")
    require_priors([candidates(args)], priors)
    return source, (priors, roi), (int(size[0]), int(size[1]))


def compute_counts(
    args: GuaranteeOptions, source: tuple, indices: range, shift: Shift | None = None
) -> dict[str, Any]:
    """(len(indices), K, 2) per-image counts of the target ("target") and of --maximize, with
    ``source`` = (network, (priors, RoI map), size) from :func:`load_source`, the images seen
    through ``shift`` if given."""
    source, (priors, roi), size = source
    scenes = StreetScenes("test", indices.stop, size, args.scene_seed)
    if shift is not None:
        scenes = ShiftedDataset(scenes, shift, args.seed)
    loader = DataLoader(Subset(scenes, indices), args.batch_size, **workers.loader_options(1))
    group, device = candidates(args), resolve_device(args.device)
    out: dict[str, list[torch.Tensor]] = {"target": [], "maximize": []}
    with torch.inference_mode(), workers.loader_errors(f"scenes {indices.start}-{indices.stop}"):
        batches = tqdm(loader, f"images {indices.start}-{indices.stop}", unit="batch")
        for b, (images, labels) in enumerate(batches):
            images, labels = images.to(device), labels.to(device)
            first = indices.start + b * args.batch_size
            names = [f"scene{first + i}" for i in range(len(images))]
            preds = group.decide(source.probabilities_of(source.scores(images, names)), priors)
            for key, spec in (("target", args.target_spec), ("maximize", args.max_spec)):
                out[key].append(per_image_counts(preds, labels, roi, *spec[:3]).cpu())
    return {k: torch.cat(v).numpy() for k, v in out.items()}


def cached_counts(
    args: GuaranteeOptions, shift: Shift | None = None
) -> tuple[dict[str, np.ndarray], str, float]:
    """(counts of the pool's images, network name, seconds spent); ``counts.npz`` in --output_dir
    keeps those of earlier runs with the same settings, so only new images are counted. With
    ``shift``: the test images alone, seen through it (``counts_<name>_<severity>.npz``)."""
    paths = checkpoints(args)
    members = [f"costseg:{p}" for p in paths if args.ckpt_path is not None or not args.network]
    name = " + ".join([*members, *(args.network or [])])
    names = ("scene_seed", "size", "sweep", "vertices", "vertex_scaling", "defer_sweep", "cost")
    key = {k: getattr(args, k) for k in names}
    key |= {"network": name, "checkpoints": [[str(p), p.stat().st_mtime] for p in paths]}
    key |= {"target": list(args.target_spec[:3]), "maximize": list(args.max_spec)}
    key |= {} if shift is None else {"shift": str(shift), "seed": args.seed}
    file = "counts.npz" if shift is None else f"counts_{shift.name}_{shift.severity}.npz"
    key_text, cache = json.dumps(key, sort_keys=True), args.output_dir / file
    counts, need, seconds = None, args.test + (0 if shift else args.cal_pool), 0.0
    if cache.is_file():
        with np.load(cache) as cached:
            if str(cached["key"]) == key_text:
                counts = {k: cached[k] for k in ("target", "maximize")}
    have, start = 0 if counts is None else len(counts["target"]), time.perf_counter()
    source = load_source(args, paths) if have < need else None
    for lo in range(have, need, 256):  # saved every 256 images: an interrupted run resumes
        new = compute_counts(args, source, range(lo, min(lo + 256, need)), shift)
        counts = new if counts is None else {k: np.concatenate([counts[k], new[k]]) for k in new}
        args.output_dir.mkdir(parents=True, exist_ok=True)
        np.savez_compressed(cache, key=np.array(key_text), **counts)
        seconds = time.perf_counter() - start
    return {k: v[:need] for k, v in counts.items()}, name, seconds


def pooled(counts: np.ndarray) -> np.ndarray:
    """(K,) pooled metric Σ numerators / Σ denominators of (n, K, 2) counts; NaN for 0/0."""
    part, whole = counts.sum(0).T.astype(float)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(whole > 0, part / whole, np.nan)


def draw_sets(args: GuaranteeOptions) -> tuple[np.ndarray, bool]:
    """(trials, n) pool indices of the calibration sets, and whether they are disjoint."""
    rng = np.random.default_rng(args.draw_seed)
    calib = np.arange(args.test, args.test + args.cal_pool)
    if args.cal_pool >= args.trials * args.n:
        return rng.permutation(calib)[: args.trials * args.n].reshape(args.trials, args.n), True
    return np.stack([rng.choice(calib, args.n, replace=False) for _ in range(args.trials)]), False


def choose(
    args: GuaranteeOptions, group: RuleGroup, target: np.ndarray, goal: np.ndarray
) -> dict[str, Any]:
    """LTT's and the naive rule's choice on one calibration set's (n, K, 2) counts."""
    losses = per_image_loss(target, args.target_spec.metric).numpy()
    ltt = learn_then_test_paths(  # as evaluate.py --guarantee
        losses, args.alpha, args.guarantee, args.guarantee_method, group.paths, args.bound
    )
    objective = pooled(goal)
    chosen = ltt.best(np.nan_to_num(objective, nan=-np.inf), prefer=group.prefer)
    allowed = meets(torch.from_numpy(pooled(target)), args.target_spec)
    naive = best_points(torch.from_numpy(objective), allowed, group.prefer)  # as --target
    return {"ltt": chosen, "naive": naive[0] if naive else None,
            "certified": len(ltt.valid), "left_out": float(ltt.n_undefined.mean())}  # fmt: skip


def summarise(
    args: GuaranteeOptions,
    counts: dict[str, np.ndarray],
    test_counts: dict[str, np.ndarray] | None = None,
) -> dict[str, Any]:
    """Every number of the check: per candidate on the test set, per trial and aggregated. The
    test set's counts are ``test_counts`` (the shifted test images) or the pool's first images."""
    test_counts = test_counts or {k: v[: args.test] for k, v in counts.items()}
    test_losses = per_image_loss(test_counts["target"], args.target_spec.metric).numpy()
    defined = (~np.isnan(test_losses)).sum(0)
    with np.errstate(invalid="ignore"):
        risk = np.nansum(test_losses, 0) / defined  # NaN where no image has a defined loss
        risk_se = np.nanstd(test_losses, 0) / np.sqrt(defined)
    goal, target = pooled(test_counts["maximize"]), pooled(test_counts["target"])
    sets, disjoint, group = *draw_sets(args), candidates(args)
    trials = [choose(args, group, counts["target"][s], counts["maximize"][s])
              for s in tqdm(sets, "calibration sets", unit="set")]  # fmt: skip
    ok = np.flatnonzero((risk <= args.alpha) & ~np.isnan(goal))
    test = {"images": args.test, "risk": risk, "risk_se": risk_se, "maximize": goal,
            "target_pooled": target, "meeting_alpha": len(ok),
            "undefined_images": [int(args.test - defined.max()), int(args.test - defined.min())],
            "best_meeting_alpha": int(ok[np.argmax(goal[ok])]) if len(ok) else None}  # fmt: skip
    settings = {k: v for k, v in vars(args).items() if not k.endswith("_spec") and k != "shifts"}
    out: dict[str, Any] = {"settings": settings, "disjoint_sets": disjoint, "test": test}
    pooled_ok = meets(torch.from_numpy(target), args.target_spec).numpy()
    for rule in RULES:
        out[rule] = rule_summary(args, [t[rule] for t in trials], test, pooled_ok)
    out["ltt"]["mean_certified"] = float(np.mean([t["certified"] for t in trials]))
    out["calibration_left_out_mean"] = float(np.mean([t["left_out"] for t in trials]))
    out["minimum_n"] = minimum_n(args, len(risk), len(group.paths))
    out["candidates"] = group.columns
    return out


def rule_summary(
    args: GuaranteeOptions, chosen: list[int | None], test: dict[str, Any], pooled_ok: np.ndarray
) -> dict[str, Any]:
    """Violations and achieved test values of one rule's choices over the trials."""
    picked = np.array([c for c in chosen if c is not None], dtype=np.int64)
    risks, values = test["risk"][picked], test["maximize"][picked]
    violations = int((risks > args.alpha).sum())  # a NaN risk counts as no violation
    rate = violations / len(chosen)
    return {"chosen": chosen, "nothing_chosen": len(chosen) - len(picked),
            "violations": violations, "violation_rate": rate,
            "violation_se": math.sqrt(rate * (1 - rate) / len(chosen)),
            "pooled_violations": int((~pooled_ok[picked]).sum()),
            "test_risk": risks, "test_maximize": values,
            "mean_test_maximize": float(np.nanmean(values)) if len(values) else None}  # fmt: skip


def minimum_n(args: GuaranteeOptions, candidates: int, paths: int = 0) -> int:
    """Fewest calibration images with which a zero empirical risk is certified (fixed-sequence
    testing along ``paths`` paths: δ / paths for each)."""
    tests = tests_sharing_delta(args.guarantee_method, candidates, paths)
    return minimum_images(args.alpha, args.guarantee, tests, args.bound)


def report(out: dict[str, Any]) -> None:
    """Print the findings."""
    s, t = out["settings"], out["test"]
    alpha, delta, trials = s["alpha"], s["guarantee"], s["trials"]
    sets = "disjoint (independent)" if out["disjoint_sets"] else "overlapping, from one pool"
    print(f"target {s['target']} (α = {alpha:.4g}), δ = {delta:g}, {s['guarantee_method']}, "
          f"{s['bound']}")  # fmt: skip
    print(f"{trials} calibration sets of {s['n']} images ({sets}); {t['images']} test images")
    lo, hi = t["undefined_images"]
    print(f"undefined loss, left out: {lo}-{hi} test images per λ; on average "
          f"{out['calibration_left_out_mean']:.1f} of {s['n']} calibration images")  # fmt: skip
    print(f"candidates with test risk <= α: {t['meeting_alpha']} of {len(t['risk'])}")
    if s["n"] < out["minimum_n"]:
        print(f"note: LTT cannot certify anything with n < {out['minimum_n']} (even at zero risk)")
    report_rules(out)


def report_rules(out: dict[str, Any]) -> None:
    """Print each rule's violations on the test set and whether the guarantee holds."""
    s = out["settings"]
    delta, trials = s["guarantee"], s["trials"]
    for rule, name in RULES.items():
        r = out[rule]
        mean = "n/a" if r["mean_test_maximize"] is None else f"{r['mean_test_maximize']:.4f}"
        print(f"{name:16s} R_test > α in {r['violations']}/{trials} = {r['violation_rate']:.3f}"
              f" ± {r['violation_se']:.3f} (pooled test target missed {r['pooled_violations']}),"
              f" nothing chosen {r['nothing_chosen']}, mean {s['maximize']} {mean}")  # fmt: skip
    bound = delta + 2 * math.sqrt(delta * (1 - delta) / trials)
    verdict = "holds" if out["ltt"]["violation_rate"] <= bound else "FAILS"
    print(f"P(R_test(λ̂) > α) <= δ {verdict}: LTT rate vs δ + 2 SE(δ) = {bound:.3f}")


def plot(out: dict[str, Any], path: Path) -> None:
    """Test risk of the chosen λ (histogram) and every λ's test risk and --maximize."""
    s, t = out["settings"], out["test"]
    left, right = (fig := Figure(figsize=(11, 4))).subplots(1, 2)
    risks = {rule: out[rule]["test_risk"][np.isfinite(out[rule]["test_risk"])] for rule in RULES}
    edges = np.histogram_bin_edges([s["alpha"], *risks["ltt"], *risks["naive"]], 30)
    right.scatter(t["risk"], t["maximize"], s=8, color="0.6", label="every candidate")
    for (rule, name), colour in zip(RULES.items(), ("tab:blue", "tab:orange"), strict=True):
        r = out[rule]
        label = f"{name} ({r['violation_rate']:.0%} of sets violate)"
        left.hist(risks[rule], bins=edges, alpha=0.6, color=colour, label=label)
        picked, freq = np.unique(np.array([c for c in r["chosen"] if c is not None], np.int64),
                                 return_counts=True)  # fmt: skip
        right.scatter(t["risk"][picked], t["maximize"][picked], s=300 * freq / s["trials"],
                      color=colour, alpha=0.5, label=f"{name}'s choices")  # fmt: skip
    for ax in (left, right):
        ax.axvline(s["alpha"], color="k", ls="--", lw=1, label="α")
        ax.legend(fontsize=8)
    title = f"{s['target']}: α = {s['alpha']:.3g}, δ = {s['guarantee']:g}, n = {s['n']}"
    left.set(xlabel="test risk of the chosen λ", ylabel="calibration sets", title=title)
    right.set(xlabel="test risk", ylabel=f"test {s['maximize']}", title="area: how often chosen")
    fig.tight_layout()
    save_figure(fig, path)


def main(argv: list[str] | None = None) -> int:
    with user_errors():  # a bad option or file: one line, exit status 2
        args = parse_args(argv)
        counts, name, seconds = cached_counts(args)
        shifted = {str(shift): cached_counts(args, shift)[0] for shift in args.shifts}
    out = summarise(args, counts) | {"network": name, "count_seconds": seconds}
    out["shifts"] = {shift: summarise(args, counts, test) for shift, test in shifted.items()}
    write_json(args.output_dir / "guarantee_check.json", out)
    plot(out, args.output_dir / "guarantee_check.png")
    report(out)
    for shift, under in out["shifts"].items():
        print(f"test images seen through {shift}:")
        report_rules(under)
    print(f"wrote {args.output_dir}/guarantee_check.json and guarantee_check.png")
    return 0


if __name__ == "__main__":
    sys.exit(main())
