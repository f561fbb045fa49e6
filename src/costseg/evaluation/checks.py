"""The refusals of an evaluation's options, before a network is loaded or data is read.

Every check here fails with a ValueError whose one line says what was expected; nothing here
builds what the plan builds (:mod:`costseg.evaluation.plan`: rule groups, priors), though a
check may be given them.
"""

from __future__ import annotations

import re
from pathlib import Path

from costseg.calibration.guarantee import minimum_images, tests_sharing_delta
from costseg.calibration.pareto_testing import images_needed
from costseg.classes import CLASS_NAMES, class_indices
from costseg.data.priors import check_priors_file
from costseg.evaluation.analyses import held_out_flags
from costseg.evaluation.priors import no_priors
from costseg.evaluation.settings import DesignSettings, SweepChoice, design_settings
from costseg.metrics.requirements import Requirements
from costseg.metrics.selection import certifiable_level, parse_metric, parse_target
from costseg.networks.probs_files import DATA_RECORD, records_its_data
from costseg.networks.protocols import OPTIONS, Protocol
from costseg.networks.sources import resolve_device
from costseg.options import EvalOptions, candidate_flags, changed, check_needs, check_values
from costseg.report.outputs import check_free
from costseg.rules import RuleGroup, named_group, parse_rules, plain_rules, vertex_matrices
from costseg.rules.design_spaces import (
    aggregate_template,
    constraint_kind,
)


def check_options(opts: EvalOptions) -> None:
    """Fail on malformed or contradictory options (those that need the rule groups:
    :func:`check_groups`)."""
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
    _check_meta(opts)
    check_design(opts)
    check_monitor(opts)
    _check_calibration(opts)
    if opts.output_dir is not None:
        check_free(opts.output_dir, opts.overwrite)


def check_groups(opts: EvalOptions, groups: list[RuleGroup]) -> None:
    """Fail on options that the rule groups they ask for cannot serve: a sweep's choice
    without one sweep to choose from, rules that need priors the data cannot give."""
    check_selection(opts, groups)
    _check_priors(opts, groups)
    if opts.conformal is not None and opts.conformal_loss == "cost":
        plain_rules(named_group(groups).rules, "--conformal_loss cost (class weights of a matrix)")


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
        monitor = opts.monitor_require and opts.monitor_space == "regional"
        regional = "--design regional" if opts.design == "regional" else (
            "--monitor_space regional" if monitor else None)  # fmt: skip
        why = f"{regional} gives each RoI its own matrix and needs a RoI map: " if regional else ""
        raise ValueError(why + no_priors(opts.data_root, geometric=opts.roi != "geometric"))


def check_selection(opts, groups: list[RuleGroup]) -> None:
    """``--target`` and ``--guarantee`` choose among the rules of the one rule group that has
    candidates (a sweep); the target's risk level α lies in (0, 1). ``opts`` is any options
    object with ``target``, ``maximize`` and ``guarantee`` (scripts/check_guarantee.py's too)."""
    if opts.guarantee is not None and not opts.target:
        raise ValueError("--guarantee needs --target (what to certify) and --maximize")
    if not (opts.target or opts.maximize):
        return
    if not (opts.target and opts.maximize):
        raise ValueError("--target and --maximize go together")
    if len(opts.target) > 1:
        raise ValueError(
            "a sweep's point is chosen for one --target; several constraints are the "
            "requirements of a design (--design SPACE --require ...)"
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
    parse_target(opts.target[0])
    parse_metric(opts.maximize)
    if opts.guarantee is not None:
        certifiable_level(opts.target[0], "--target")


def check_design(opts: EvalOptions) -> None:
    """``--design``: its requirements (``--require``, ``--design_maximize`` /
    ``--design_minimize``), δ, and a space that can be built from them (docs/definitions.md
    §20)."""
    if opts.design is None:
        return
    if not opts.require or opts.design_delta is None:
        raise ValueError(
            "--design needs its requirements: --require (one or more) and --design_delta δ "
            "(--target, --maximize and --guarantee choose a point of a sweep)"
        )
    req = Requirements.parse(opts.require, opts.design_maximize, opts.design_minimize)
    twice = sorted({t for t in req.constraints if req.constraints.count(t) > 1}, key=str)
    if twice:
        text = req.texts[req.constraints.index(twice[0])]
        raise ValueError(f"--require gives {text} twice: each requirement once")
    same = [t[:3] for t in req.constraints]
    if len(set(same)) < len(same):
        text = req.texts[next(i for i, t in enumerate(same) if same.count(t) > 1)]
        raise ValueError(
            f"--require gives two levels for the rate of {text}: keep the stricter one"
        )
    if opts.limit is not None and opts.calibration_split is None:  # at most half of --limit
        check_design_size(design_settings(opts), opts.limit // 2, own_split=False)
    vertex_matrices(opts.vertices, opts.vertex_scaling)  # the triangle, searched to compare
    if opts.design in ("lagrangian", "regional"):
        for t in req.constraints:
            constraint_kind(t.metric)
        bases = parse_rules([opts.design_base or "robotistic"])
        base = (bases if opts.design == "regional" else plain_rules(bases, "--design_base"))[0]
        if base.priors_alpha or (base.defers and opts.design_defer):
            raise ValueError(
                f"--design_base {base.name}: C0 of --design {opts.design} is a cost matrix (not "
                "ml)" + (", without a defer row when --design_defer gives one" if base.defers
                         else "")
            )  # fmt: skip
    elif opts.design == "aggregate":
        aggregate_template(opts.design_base or "altruistic")
    elif opts.design_base is not None:
        raise ValueError("--design_base goes with --design lagrangian, regional or aggregate")


def check_monitor(opts: EvalOptions) -> None:
    """``--monitor_require``: its requirements (recall or precision of one class, each once),
    C₀, the start's multipliers within the cap, and (with ``--limit``) a stream that the delay
    and ``--shift_onset`` fit in (docs/definitions.md §22)."""
    from costseg.metrics.monitor import (
        Monitor,
        base_matrix,
        monitored_requirements,
        start_multipliers,
    )

    if opts.shift_onset is not None and opts.limit is not None:
        check_stream(opts.shift_onset, 0, opts.limit)
    if not opts.monitor_require:
        return
    req = monitored_requirements(opts.monitor_require)
    same = [t[:3] for t in req.constraints]
    if len(set(same)) < len(same):
        text = req.texts[next(i for i, t in enumerate(same) if same.count(t) > 1)]
        raise ValueError(f"--monitor_require gives the rate of {text} twice: keep one level")
    try:
        base = base_matrix(opts.monitor_base, regional=opts.monitor_space == "regional")
    except ValueError as err:
        raise ValueError(f"--monitor_base {err}") from None
    if opts.monitor_start is not None:
        if not Path(opts.monitor_start).is_file():
            raise ValueError(f"--monitor_start: no such file {opts.monitor_start}")
        space = Monitor(opts.monitor_require, base=base, mu_max=opts.monitor_max,
                        space=opts.monitor_space).space()  # fmt: skip
        mu = start_multipliers(opts.monitor_start, space)
        if (mu > opts.monitor_max).any():
            raise ValueError(
                f"--monitor_start {opts.monitor_start}: its multipliers {mu.round(4).tolist()} "
                f"exceed --monitor_max {opts.monitor_max:g}"
            )
    if opts.limit is not None:
        check_stream(opts.shift_onset, opts.monitor_delay, opts.limit)


def check_stream(onset: int | None, delay: int, frames: int) -> None:
    """A stream of ``frames`` reported images long enough for ``--shift_onset`` (a frame
    clean before the shift, one shifted after it) and ``--monitor_delay`` (a label that arrives
    before the end).

    >>> check_stream(5, 0, 5)
    Traceback (most recent call last):
    ValueError: --shift_onset 5: the stream has 5 reported images, so no image would be shifted
    """
    if onset is not None and onset >= frames:
        raise ValueError(
            f"--shift_onset {onset}: the stream has {frames} reported images, so no image "
            "would be shifted"
        )
    if delay >= frames:
        raise ValueError(
            f"--monitor_delay {delay}: the stream has {frames} reported images, so no label "
            "would arrive before its end"
        )


def _check_meta(opts: EvalOptions) -> None:
    if opts.fuse and any(r.defers for r in parse_rules([opts.fuse_base, *opts.fuse])):
        raise ValueError("--fuse and --fuse_base take rules that never defer")
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


def check_calibration_size(
    choice: SweepChoice, n_images: int, candidates: RuleGroup, own_split: bool
) -> None:
    """Refuse a guarantee that cannot certify anything with ``n_images`` calibration images
    (of ``--calibration_split`` when ``own_split``) among the rules of ``candidates``
    (Bonferroni over them, or over its fixed-sequence paths). A design has its own check
    (:func:`check_design_size`)."""
    alpha, family = certifiable_level(choice.target, "--target"), len(candidates.names)
    tests = tests_sharing_delta(choice.method, family, len(candidates.paths))
    needed = minimum_images(alpha, choice.delta, tests)
    if n_images < needed:
        more = "" if own_split else "--calibration_split (another split's images), "
        raise ValueError(
            f"{n_images} calibration images cannot certify anything at α = {alpha:.3g}, "
            f"δ = {choice.delta} over {family} candidates: at least {needed} are needed; give "
            f"{more}a looser --target, a larger --guarantee δ or a coarser sweep"
        )


def check_design_size(settings: DesignSettings, n_images: int, own_split: bool) -> None:
    """Refuse a design whose certification half cannot certify anything, not even a matrix
    with no loss on any image: the certification images (D2, half of the ``n_images`` held-out
    images, those of ``--calibration_split`` when ``own_split``) must number at least the
    smallest n at which a risk of 0 passes the strictest requirement at δ."""
    req = Requirements.parse(settings.requirements, settings.maximize, settings.minimize)
    alpha = min(req.alphas)
    per_half = images_needed(0.0, alpha, settings.delta)
    if n_images // 2 >= 1 and n_images - n_images // 2 >= per_half:
        return
    needed = 2 * per_half
    more = (
        "a split with more images"  # --limit does not cut --calibration_split
        if own_split
        else "--calibration_split (another split's images) or a larger --limit"
    )
    raise ValueError(
        f"{n_images} held-out image(s) ({settings.held_out}) cannot certify a design at "
        f"α = {alpha:.3g}, δ = {settings.delta}: half of them certify, and even with no loss "
        f"on any image {per_half} are needed there, so at least {needed} held-out images; give "
        f"{more}, or a looser --require / --design_delta"
    )


def check_instance_targets(opts: EvalOptions, measured: list[int], note: str) -> None:
    """ValueError when a target, requirement or objective asks for an instance metric of a
    class whose instances are not ``measured`` (``note`` says why)."""
    texts = (*(opts.target or ()), *(opts.require or ()), opts.maximize, opts.design_maximize,
             opts.design_minimize)  # fmt: skip
    for text in texts:
        metric = parse_metric(re.split(r"[<>=]", text)[0]) if text else None
        if metric and metric.metric == "instance_recall" and metric.cls not in measured:
            name = CLASS_NAMES[metric.cls]
            raise ValueError(f"{text} needs instance ids and {name!r} in --classes ({note})")
