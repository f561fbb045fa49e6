"""What the evaluation plan decides before any image: valid options, rule groups, priors.

Every check here fails with a ValueError whose one line says what was expected, so a user
mistake is reported before a network is loaded.
"""

from __future__ import annotations

import re
from pathlib import Path

import torch

from costseg.calibration.guarantee import minimum_images, tests_sharing_delta
from costseg.classes import CLASS_NAMES, INSTANCE_CLASSES, class_indices
from costseg.data.from_config import same_data
from costseg.data.priors import check_priors_file
from costseg.evaluation.analyses import held_out_flags
from costseg.metrics.requirements import Requirements
from costseg.metrics.selection import parse_metric, parse_target, risk_level
from costseg.networks.probs_files import DATA_RECORD, records_its_data
from costseg.networks.protocols import OPTIONS, Protocol
from costseg.networks.sources import resolve_device
from costseg.options import EvalOptions, candidate_flags, changed, check_needs, check_values
from costseg.report.outputs import check_free
from costseg.rules import (
    TEMPERATURES,
    RuleGroup,
    alpha_group,
    defer_costs,
    defer_group,
    grid_group,
    parse_rules,
    rules_group,
    temperature_group,
    vertex_matrices,
)
from costseg.rules.design_spaces import aggregate_template, constraint_kind


def check_options(opts: EvalOptions) -> list[RuleGroup]:
    """Fail on malformed or contradictory options; returns the rule groups they ask for."""
    check_values(opts)
    class_indices(opts.classes)
    resolve_device(opts.device)
    check_needs(opts)
    if opts.probs is not None and (opts.ckpt_path is not None or opts.network is not None):
        raise ValueError("--probs replaces the network: give it without --ckpt_path and --network")
    if opts.probs is not None and not Path(opts.probs).is_dir():
        raise ValueError(f"--probs folder not found: {opts.probs}")
    if opts.probs is not None and opts.data_root is None and not records_its_data(opts.probs):
        raise ValueError(
            f"--probs needs --data_root: {opts.probs} does not say which images were scored "
            f"(a --save-probs folder does, in its {DATA_RECORD})"
        )
    if opts.mc_dropout is not None and opts.probs is not None:
        raise ValueError("--mc_dropout needs a network: saved probabilities cannot be resampled")
    if Protocol.from_options(opts) != Protocol() and opts.probs is not None:
        raise ValueError(f"{OPTIONS} need a network: saved probabilities cannot be rerun")
    if opts.shift and opts.probs is not None:
        raise ValueError("--shift needs a network: saved probabilities cannot see other images")
    check_shifts(opts.shift)
    if opts.save_probs and opts.probs is not None:
        raise ValueError("--save-probs writes a network's probabilities; with --probs they exist")
    rules = parse_rules(opts.cost, defer=opts.defer)  # the sweeps' rules never defer
    groups = [rules_group(rules)]
    if opts.defer_sweep is not None:  # first: the candidates of --target and --guarantee
        groups.append(defer_group(opts.cost, defer_costs(*opts.defer_sweep)))
    if opts.sweep is not None:
        groups.append(grid_group(opts.vertices, opts.sweep, opts.vertex_scaling))
    if opts.alpha_sweep is not None:
        groups.append(alpha_group(opts.alpha_sweep, opts.alpha_cost))
    if opts.temperature_sweep:
        groups += [temperature_group(rules, t) for t in TEMPERATURES]
    if opts.fuse:
        groups.append(_fusion_group(opts))
    _check_meta(opts)
    check_selection(opts, groups)
    check_design(opts)
    _check_calibration(opts)
    _check_priors(opts, groups)
    if opts.output_dir is not None:
        check_free(opts.output_dir, opts.overwrite)
    return groups


def check_shifts(shifts: list[str]) -> None:
    """Each ``--shift`` a known corruption and severity
    (:func:`costseg.data.shift.parse_shift`), none named twice."""
    from costseg.data.shift import parse_shift

    for text in shifts:
        parse_shift(text)
    if len(set(shifts)) < len(shifts):
        raise ValueError(f"--shift names a shift twice: {' '.join(shifts)}")


def _check_priors(opts: EvalOptions, groups: list[RuleGroup]) -> None:
    """A ``--priors`` file that exists; and, for a Cityscapes root without a train split to
    count priors from, ``--priors`` or ``--roi geometric`` (docs/definitions.md §3)."""
    check_priors_file(opts.priors)
    if opts.priors is not None:
        return
    if opts.data_root is None or (Path(opts.data_root) / "gtFine" / "train").is_dir():
        return
    if opts.roi != "geometric" or any(g.needs_priors for g in groups):
        raise ValueError(no_priors(opts.data_root, geometric=opts.roi != "geometric"))


def no_priors(data: str, geometric: bool = True) -> str:
    """The one line that refuses a run whose data has no priors to offer."""
    return (
        f"no pixel-wise priors for {data}: no train split to count them from (gtFine/train); "
        "pass --priors FILE (a run's priors.pt, or scripts/count_priors.py's from a label folder)"
        + (" or --roi geometric (then no ml, no --alpha_sweep)" if geometric else "")
    )


def check_selection(opts: EvalOptions, groups: list[RuleGroup]) -> None:
    """``--target`` and ``--guarantee`` choose among the rules of the one rule group that has
    candidates (a sweep); δ and the target's risk level α lie in (0, 1). ``opts`` is any options
    object with ``target``, ``maximize`` and ``guarantee`` (scripts/check_guarantee.py's too);
    with ``--design`` they are the design's (:func:`check_design`)."""
    if getattr(opts, "design", None):
        return
    if opts.guarantee is not None:
        if not 0 < opts.guarantee < 1:
            raise ValueError(f"--guarantee is δ and must lie in (0, 1), got {opts.guarantee}")
        if not opts.target:
            raise ValueError("--guarantee needs --target (what to certify) and --maximize")
    if not (opts.target or opts.maximize or opts.guarantee is not None):
        return
    if not (opts.target and opts.maximize):
        raise ValueError("--target and --maximize go together")
    if len(opts.target) > 1:
        raise ValueError(
            "several --target constraints are the requirements of a design (evaluate.py "
            "--design SPACE); a sweep's point is chosen for one"
        )
    choosing = "--guarantee" if opts.guarantee is not None else "--target"
    candidates = [g.family for g in groups if g.candidates]
    if not candidates:
        raise ValueError(f"{choosing} chooses among the points of a sweep: {candidate_flags()}")
    if len(candidates) > 1:
        raise ValueError(
            f"{choosing} chooses among the points of one sweep; these options give "
            f"{len(candidates)} ({', '.join(candidates)}): keep one of {candidate_flags()}"
        )
    target = parse_target(opts.target[0])
    parse_metric(opts.maximize)
    if opts.guarantee is not None and not 0 < risk_level(target) < 1:
        raise ValueError(f"--target {opts.target[0]} leaves no risk level α in (0, 1)")


def check_design(opts: EvalOptions) -> None:
    """``--design``: its requirements (``--target``, ``--maximize`` / ``--minimize``), δ, and a
    space that can be built from them (docs/definitions.md §20)."""
    if opts.design is None:
        return
    if not opts.target or opts.guarantee is None:
        raise ValueError(
            "--design needs its requirements: --target (one or more) and --guarantee δ"
        )
    if not 0 < opts.guarantee < 1:
        raise ValueError(f"--guarantee is δ and must lie in (0, 1), got {opts.guarantee}")
    if opts.design_pixels > 1:
        raise ValueError(f"--design_pixels is a share in (0, 1], got {opts.design_pixels}")
    req = Requirements.parse(opts.target, opts.maximize, opts.minimize)
    vertex_matrices(opts.vertices, opts.vertex_scaling)  # the triangle, searched to compare
    if opts.design == "lagrangian":
        for t in req.constraints:
            constraint_kind(t.metric)
        base = parse_rules([opts.design_base or "robotistic"])[0]
        if base.priors_alpha or (base.defers and opts.design_defer):
            raise ValueError(
                f"--design_base {base.name}: C0 of --design lagrangian is a cost matrix (not ml)"
                + (", without a defer row when --design_defer gives one" if base.defers else "")
            )
    elif opts.design == "aggregate":
        aggregate_template(opts.design_base or "altruistic")
    elif opts.design_base is not None:
        raise ValueError("--design_base goes with --design lagrangian or aggregate")


def _fusion_group(opts: EvalOptions) -> RuleGroup:
    from costseg.meta.fusion import fusion_group  # numba's segment passes: only with --fuse

    base = parse_rules([opts.fuse_base])[0]
    fused = parse_rules(opts.fuse)
    if any(r.defers for r in (base, *fused)):
        raise ValueError("--fuse and --fuse_base take rules that never defer")
    return fusion_group(base, fused, opts.fuse_tau, class_indices(opts.fuse_classes))


def _check_meta(opts: EvalOptions) -> None:
    for lone, needed in (
        ([] if opts.fuse else changed(opts, ["fuse_base", "fuse_tau", "fuse_classes"]), "--fuse"),
        ([] if opts.meta or opts.fuse else changed(opts, ["meta_split", "meta_images"]),
         "--meta or --fuse"),
    ):  # fmt: skip
        if lone:
            verb = "goes" if len(lone) == 1 else "go"
            raise ValueError(f"{', '.join(lone)} {verb} with {needed}")
    if opts.meta_split is not None and opts.meta_split == opts.split:
        raise ValueError(
            f"--meta_split {opts.meta_split} overlaps the reported split {opts.split}: the meta "
            "models must be fitted on other images"
        )
    if (opts.meta or opts.fuse) and opts.probs is not None and opts.meta_split is not None:
        raise ValueError("--meta_split needs a network: saved probabilities cover one split")
    if opts.fuse and opts.guarantee is not None and opts.meta_split is None:
        raise ValueError(
            "--guarantee over --fuse certifies on held-out images, which must not be the ones "
            "that fit the meta classifier: give --meta_split"
        )


def _check_calibration(opts: EvalOptions) -> None:
    if opts.calibrate not in (None, "temperature", "vector"):
        raise ValueError(f"--calibrate must be temperature or vector, got {opts.calibrate!r}")
    if opts.calibration_split is not None:
        if not (held_out_flags(opts) or opts.meta or opts.fuse):
            flags = ", ".join(held_out_flags())
            raise ValueError(f"--calibration_split goes with {flags}, --meta or --fuse")
        if opts.calibration_split == opts.split:
            raise ValueError(
                f"--calibration_split {opts.calibration_split} overlaps the reported split "
                f"{opts.split}: calibration images must be disjoint from the reported ones"
            )


def check_calibration_size(opts: EvalOptions, n_images: int, candidates: RuleGroup) -> None:
    """Refuse a guarantee that cannot certify anything with ``n_images`` calibration images
    among the rules of ``candidates`` (Bonferroni over them, or over its fixed-sequence paths)."""
    if opts.guarantee is None:
        return
    if opts.design:  # too few images is a result of the design: it says how many it needs
        return
    alpha, family = risk_level(parse_target(opts.target[0])), len(candidates.names)
    tests = tests_sharing_delta(opts.guarantee_method, family, len(candidates.paths))
    needed = minimum_images(alpha, opts.guarantee, tests)
    if n_images < needed:
        more = "" if opts.calibration_split else "--calibration_split (another split's images), "
        raise ValueError(
            f"{n_images} calibration images cannot certify anything at α = {alpha:.3g}, "
            f"δ = {opts.guarantee} over {family} candidates: at least {needed} are needed; give "
            f"{more}a looser --target, a larger --guarantee δ or a coarser sweep"
        )


def instance_classes(dataset, opts: EvalOptions) -> tuple[list[int], str]:
    """The instance classes among ``--classes`` whose misses are measured (none when the
    dataset has no instance ids), and a line saying so for the outputs; ValueError when
    ``--target`` / ``--maximize`` ask for an instance metric that cannot be measured."""
    chosen = [c for c in class_indices(opts.classes) if c in INSTANCE_CLASSES]
    note = f"instance metrics for {', '.join(CLASS_NAMES[c] for c in chosen)} (definitions §9)"
    if not getattr(dataset, "has_instances", False):
        missing = getattr(dataset, "missing_instances", None)
        why = f"{missing} of {len(dataset)} images have" if missing else "the dataset has"
        chosen, note = [], f"instance metrics absent: {why} no instance ids (*_instanceIds.png)"
    elif not chosen:
        note = "instance metrics absent: no instance class among --classes"
    for text in (*(opts.target or ()), opts.maximize, opts.minimize):
        metric = parse_metric(re.split(r"[<>=]", text)[0]) if text else None
        if metric and metric.metric == "instance_recall" and metric.cls not in chosen:
            name = CLASS_NAMES[metric.cls]
            raise ValueError(f"{text} needs instance ids and {name!r} in --classes ({note})")
    return chosen, note


def source_priors(
    source, opts: EvalOptions, data: dict | None, cache_dir: Path
) -> torch.Tensor | None:
    """The pixel-wise priors of the evaluated ``data`` (docs/definitions.md §3, §8): the
    ``--priors`` file; the source's own when they were counted on this data (a checkpoint's,
    or those saved beside probabilities; for a dataset given in Python, ``data`` None, those
    given with it); else counted once from the data's train labels and cached in ``cache_dir``
    (next to the outputs). None only with ``--roi geometric`` and no train labels; never
    another dataset's priors."""
    if opts.priors is not None:
        from costseg.data.priors import read_priors_file

        priors = read_priors_file(opts.priors, CLASS_NAMES)["priors"]
        print(f"priors read from {opts.priors}")
        source.description["priors"] = {"file": str(Path(opts.priors).resolve())}
        return priors
    if source.priors is not None and (data is None or same_data(source.data_config, data)):
        return source.priors
    if source.priors is not None:
        print("the source's priors were counted on other data: not used for this data")
    return _counted_priors(source, opts, data, cache_dir)


def _counted_priors(
    source, opts: EvalOptions, data: dict | None, cache_dir: Path
) -> torch.Tensor | None:
    from costseg.data.from_config import build_dataset, data_settings
    from costseg.data.priors_cache import settings_key, training_priors

    try:
        if data is None:
            raise FileNotFoundError("a dataset given in Python has no train split")
        train = build_dataset(data, "train")
    except FileNotFoundError:
        if opts.roi == "geometric":
            print("no training labels: no pixel-wise priors; RoIs from the geometric map")
            source.description["priors"] = "none: no training labels"
            return None
        name = "the given dataset" if data is None else data_settings(data).root
        raise ValueError(no_priors(name)) from None
    read = getattr(train, "read_label", None) or (lambda i: train[i][1])
    found = training_priors(
        lambda: (read(i) for i in range(len(train))),
        cache_dir / f"train_{settings_key(data)}.pt",
        {"data": data, "split": "train", "images": len(train)},
        progress=opts.progress,
    )
    source.description["priors"] = found.record | {"data": data, "split": "train"}
    return found.priors
