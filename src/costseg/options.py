"""Every option of the command lines, declared once as typed dataclass fields.

A field's type, default and ``metadata`` (help, flag, choices, value type, argument group) are
all the command line knows: :func:`costseg.cli.build_parser` derives the parser from them, and
the jobs receive the dataclass. :class:`NetworkOptions` holds what every job that runs a network
shares (source, rules, device, output folder, examples), :class:`SourceOptions` adds a dataset,
:class:`EvalOptions` and :class:`PredictOptions` add each command's own; :class:`ExportOptions`
takes the source options of one network.
A new option is one field here, its value type one of :mod:`costseg.values`. No heavy imports,
so ``--help`` answers at once.

>>> EvalOptions(cost=["egoistic"]).split
'val'
"""

from __future__ import annotations

import argparse
import dataclasses
import types
import typing
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Literal

from costseg.values import (
    NETWORK_USAGE,
    defer_cost,
    fraction,
    positive_number,
    share,
    step_size,
    whole_number,
)

SOURCE = "probability source (default: newest runs/**/last.ckpt; several: their ensemble)"
CALIBRATION = "calibration and guarantees (fitted on held-out images)"
PROTOCOL = "inference protocol (docs/definitions.md §13)"
SEGMENTS = "segments: meta classification and fusion (docs/definitions.md §15)"
CONFORMAL = "conformal prediction sets (docs/definitions.md §18)"
DESIGN = "designing the value system from requirements (docs/definitions.md §20)"
MONITOR = "watching the value system at run time (docs/definitions.md §22)"
RULES = ["robotistic", "altruistic", "egoistic"]


def option(default: Any = None, help: str | None = None, **metadata: Any) -> Any:
    """A dataclass field that is also a command-line option.

    Args:
        default: the default value (a list is copied for each instance).
        help: the line ``--help`` shows.
        **metadata: ``flag`` (default ``--<name>``; a name without dashes: a positional
            argument), ``type`` (a value type of :mod:`costseg.values`, such as
            :func:`~costseg.values.whole_number`), ``nargs``, ``metavar``, ``group`` (an
            argument group's title), ``candidates=True`` (the option builds a rule group whose
            rules ``--target`` and ``--guarantee`` choose among: :func:`candidate_flags`),
            ``needs`` (the option that must be given for this one to mean anything:
            :func:`check_needs`).
    """
    metadata["help"] = help
    if isinstance(default, list):
        return dataclasses.field(default_factory=lambda: list(default), metadata=metadata)
    return dataclasses.field(default=default, metadata=metadata)


def same_option(
    options: type, name: str, default: Any = dataclasses.MISSING, **metadata: Any
) -> Any:
    """Another command's option: the field ``name`` of the dataclass ``options`` (its help, flag,
    value type and check), with this command's own ``default`` and ``metadata`` where given.

    >>> @dataclass
    ... class Check:
    ...     batch_size: int = same_option(SourceOptions, "batch_size", 16)
    >>> Check().batch_size, dataclasses.fields(Check)[0].metadata["help"]
    (16, 'images per batch')
    """
    field = next(f for f in dataclasses.fields(options) if f.name == name)
    kept = field_default(field) if default is dataclasses.MISSING else default
    return option(kept, **{**field.metadata, **metadata})


def field_default(f: dataclasses.Field) -> Any:
    """The default of an options field."""
    return f.default_factory() if f.default_factory is not dataclasses.MISSING else f.default


def changed(opts: Any, names: Sequence[str]) -> list[str]:
    """The flags among the fields ``names`` of ``opts`` whose values differ from their defaults.

    >>> changed(EvalOptions(fuse_tau=[0.3]), ["fuse_tau", "fuse_base"])
    ['--fuse_tau']
    """
    fields = {f.name: f for f in dataclasses.fields(opts)}
    return [
        fields[n].metadata.get("flag", f"--{n}")
        for n in names
        if getattr(opts, n) != field_default(fields[n])
    ]


@dataclass
class NetworkOptions:
    """What every job that runs a network is told: where probabilities come from, which rules,
    on which device, where outputs go, and which examples the figures and the explorer show."""

    cost: list[str] = option(RULES, "rules: robotistic, altruistic, egoistic, ml or a .yaml cost")
    defer: float | None = option(
        help="every --cost rule may defer a pixel at this cost (docs/definitions.md §14); "
        "the rules of evaluate.py's sweeps never defer",
        type=defer_cost,
        metavar="C",
    )
    ckpt_path: list[str] | None = option(
        help="costseg checkpoints (several: their ensemble, docs/definitions.md §13)",
        metavar="PATH",
        group=SOURCE,
    )
    network: list[str] | None = option(
        help=f"{NETWORK_USAGE}; several, or with --ckpt_path: their ensemble",
        metavar="SPEC",
        group=SOURCE,
    )
    mc_dropout: int | None = option(
        help="Monte-Carlo dropout: the mean softmax of N passes with dropout active",
        type=whole_number(1),
        metavar="N",
        group=SOURCE,
    )
    seed: int = option(
        0, "seed of --mc_dropout (and of evaluate.py's --shift)", type=whole_number(0), group=SOURCE
    )
    inference: Literal["whole", "slide"] = option(
        "whole", "one forward per image, or sliding windows (--crop, --stride)", group=PROTOCOL
    )
    crop: list[int] | None = option(
        help="the windows of --inference slide",
        type=whole_number(1),
        nargs=2,
        metavar=("H", "W"),
        group=PROTOCOL,
    )
    stride: list[int] | None = option(
        help="the step between windows of --inference slide (at most --crop)",
        type=whole_number(1),
        nargs=2,
        metavar=("H", "W"),
        group=PROTOCOL,
    )
    tta: Literal["flip"] | None = option(
        help="test-time augmentation: the mean softmax with the horizontally flipped image",
        group=PROTOCOL,
    )
    scales: list[float] | None = option(
        help="test-time augmentation: the mean softmax over the image resized by each scale "
        "(default: 1 only)",
        type=positive_number,
        metavar="S",
        group=PROTOCOL,
    )
    priors: str | None = option(
        help="pixel-wise priors file (a run's priors.pt, or scripts/count_priors.py's from a "
        "label folder) for ml and the RoI map; default: a checkpoint's for its own data, else "
        "(evaluate.py) counted from the data's train labels",
        metavar="FILE",
    )
    output_dir: str | None = option(help="default: a new numbered folder <run>/<job>/version_<n>")
    overwrite: bool = option(False, "allow an --output_dir that holds results")
    device: str = option("auto", "auto, cpu, cuda, cuda:1, ...")
    save_probs: bool = option(
        False,
        "write each image's probabilities (float16 .npz) for later --probs runs",
        flag="--save-probs",
    )
    num_examples: int = option(
        3, "images in the mask figures and the explorer", type=whole_number(0)
    )
    vertices: list[str] = option(RULES, "the triangle's corners", nargs=3)
    vertex_scaling: Literal["none", "mean"] = option(
        "none", "'mean': rescale each vertex to unit mean off-diagonal cost before mixing"
    )
    explorer: bool = option(False, "also write explorer.html (docs/definitions.md §11)")
    progress: bool = option(True, "no progress lines", flag="--no-progress")


@dataclass
class SourceOptions(NetworkOptions):
    """A network's job on a labelled dataset, or saved probabilities in place of the network."""

    probs: str | None = option(
        help="folder of saved probabilities (<image>.npz or .pt)", group=SOURCE
    )
    data_root: str | None = option(
        help="Cityscapes root (needed for --network/--probs of other networks)"
    )
    split: Literal["train", "val", "test"] = option("val", "the split to run on")
    roi: Literal["priors", "geometric"] = option(
        "priors",
        "regions of interest from the priors, or the fixed geometric map of a street camera "
        "(docs/definitions.md §3) for data without training labels",
    )
    limit: int | None = option(help="only the first N images", type=whole_number(1))
    batch_size: int | None = option(help="images per batch", type=whole_number(1))


@dataclass
class EvalOptions(SourceOptions):
    """Everything ``evaluate.py`` can be told (see ``python evaluate.py --help``)."""

    classes: list[str] = option(["person", "building"], "classes of the table and segment maps")
    anomalies: bool = option(
        False,
        "evaluate on the procedural scenes with unknown objects added: anomaly scores, their "
        "pixel and component metrics, what each rule decides on them (docs/definitions.md §17)",
        flag="--anomalies",
    )
    shift: list[str] = option(
        [],
        "see the reported images through corruptions, e.g. fog:3 night:2 (severity 0-5, "
        "docs/definitions.md §17): one evaluation per shift; calibration images stay clean",
        nargs="+",
        metavar="NAME:SEVERITY",
    )
    shift_onset: int | None = option(
        help="the first N reported images stay clean and --shift starts at image N + 1: a "
        "stream whose conditions change mid-way (--monitor_require)",
        type=whole_number(1),
        metavar="N",
        needs="shift",
    )
    save_predictions: bool = option(
        False, "write Cityscapes label-id PNGs per image and rule", flag="--save-predictions"
    )
    sweep: float | None = option(
        help="also sweep the barycentric grid of this step over the three --vertices",
        type=step_size,
        metavar="STEP",
        candidates=True,
    )
    defer_sweep: list[float] | None = option(
        help="also decide every --cost rule with a defer row of each cost START, START + STEP, "
        "..., STOP: risk-coverage curves (docs/definitions.md §14)",
        type=defer_cost,
        nargs=3,
        metavar=("START", "STOP", "STEP"),
        candidates=True,
    )
    target: list[str] | None = option(
        help="constraint that chooses a point of the sweep, e.g. 'person:roi1:recall>=0.99' or "
        "'person:roi1:handled_recall>=0.99' (a design's requirements are --require)",
        nargs="+",
        metavar="CONSTRAINT",
    )
    maximize: str | None = option(
        help="what to maximise under --target, e.g. person:roi1:precision or all:roi1:coverage"
    )
    alpha_sweep: float | None = option(
        help="also sweep the prior-adapted rule from Bayes (α=0) to ML (α=1)",
        type=step_size,
        metavar="STEP",
        candidates=True,
    )
    alpha_cost: str | None = option(help="cost matrix of the α sweep (default: symmetric)")
    calibrate: Literal["temperature", "vector"] | None = option(
        help="scale the logits, fitted on the first half of the split (or --calibration_split); "
        "the second half is reported",
        group=CALIBRATION,
    )
    calibration_split: Literal["train", "val", "test"] | None = option(
        help="fit / certify on this split instead of the first half of --split", group=CALIBRATION
    )
    temperature_sweep: bool = option(
        False,
        "every named rule at T = 0.5 ... 2 (and the fitted T), the network run once",
        group=CALIBRATION,
    )
    guarantee: float | None = option(
        help="choose the --sweep / --alpha_sweep / --defer_sweep point with P(risk > α) <= DELTA "
        "(Learn-then-Test); α comes from --target",
        type=fraction,
        metavar="DELTA",
        group=CALIBRATION,
    )
    guarantee_method: Literal["bonferroni", "fixed_sequence"] = option(
        "bonferroni",
        "family-wise error control (fixed_sequence tests along the grid / α order, or each "
        "rule's defer costs from the smallest up)",
        group=CALIBRATION,
    )

    save_segments: bool = option(
        False,
        "write segments/<rule>.csv: every segment of every --cost rule with its features and "
        "targets",
        flag="--save-segments",
        group=SEGMENTS,
    )
    meta: bool = option(
        False,
        "fit meta classifiers and regressors of each --cost rule's segments on held-out images "
        "(--meta_split, --calibration_split, or the first half of --split) and score them on "
        "the reported ones",
        group=SEGMENTS,
    )
    meta_split: Literal["train", "val", "test"] | None = option(
        help="fit the meta models on this split (its first --meta_images images)", group=SEGMENTS
    )
    meta_images: int = option(
        100,
        "images of --meta_split that fit the meta models",
        type=whole_number(1),
        group=SEGMENTS,
    )
    fuse: list[str] | None = option(
        help="rules whose extra segments are fused with --fuse_base where the meta classifier "
        "trusts them (MetaFusion), e.g. ml altruistic",
        metavar="RULE",
        group=SEGMENTS,
    )
    fuse_base: str = option("robotistic", "the base rule of --fuse", group=SEGMENTS)
    fuse_tau: list[float] = option(
        [0.5],
        "thresholds τ of --fuse: candidates whose probability of being false is >= τ are "
        "dropped; several: a sweep, chosen by --target",
        type=float,
        metavar="TAU",
        group=SEGMENTS,
        candidates=True,
    )
    fuse_classes: list[str] = option(["person"], "the classes --fuse fuses", group=SEGMENTS)

    conformal: float | None = option(
        help="prediction sets anchored on each --cost rule whose expected loss on the reported "
        "images is at most ALPHA, λ chosen on held-out images (--calibration_split, or the "
        "first half of --split)",
        type=fraction,
        metavar="ALPHA",
        group=CONFORMAL,
    )
    conformal_sets: Literal["lac", "aps"] = option(
        "lac",
        "how a set grows with λ: lac (every class with p >= 1 - λ) or aps (classes by "
        "decreasing p until their mass exceeds λ)",
        group=CONFORMAL,
        needs="conformal",
    )
    conformal_loss: Literal["uniform", "cost", "binary"] = option(
        "uniform",
        "the loss controlled: the share of labelled pixels whose class is not in the set "
        "(uniform), each weighted by the anchor rule's mean cost of missing its class (cost), "
        "or 1 when the covered share is below --conformal_tau (binary)",
        group=CONFORMAL,
        needs="conformal",
    )
    conformal_tau: float = option(
        0.9,
        "the covered share of --conformal_loss binary",
        type=fraction,
        group=CONFORMAL,
        needs="conformal_loss=binary",
    )
    conformal_roi: Literal[1, 2, 3, 4] | None = option(
        help="count only the pixels of this RoI in the loss (1 street, 2 sidewalk, 3 building, "
        "4 sky: docs/definitions.md §3)",
        metavar="R",
        group=CONFORMAL,
        needs="conformal",
    )

    design: Literal["triangle", "lagrangian", "aggregate", "regional"] | None = option(
        help="design a cost matrix meeting every --require, jointly with probability 1 - δ "
        "(--design_delta): searched in this space on a random half of the held-out images "
        "(--seed), certified on the other half by Pareto Testing; writes designed_cost.yaml "
        "(regional: a matrix per RoI, each requirement moving its own RoI's; needs a RoI map)",
        group=DESIGN,
    )
    design_search: Literal["grid", "continuous"] | None = option(
        help="how --design lagrangian or regional searches its multipliers: every point of a log "
        "grid, or Optuna's TPE sampler over log μ (--seed); default: the grid when it has at "
        "least 8 values per multiplier within --design_budget, else continuous",
        group=DESIGN,
        needs="design=lagrangian|regional",
    )
    require: list[str] | None = option(
        help="the requirements of --design, e.g. 'person:roi1:recall>=0.8' "
        "'building:roi3:precision>=0.8': each met with the others, jointly with probability "
        "1 - --design_delta",
        nargs="+",
        metavar="CONSTRAINT",
        group=DESIGN,
        needs="design",
    )
    design_delta: float | None = option(
        help="δ of --design: every --require met jointly with probability >= 1 - δ",
        type=fraction,
        metavar="DELTA",
        group=DESIGN,
        needs="design",
    )
    design_maximize: str | None = option(
        help="what --design maximises among the certified matrices (default agreement, the "
        "share of pixels decided as argmax), e.g. miou or person:roi1:precision",
        group=DESIGN,
        needs="design",
    )
    design_minimize: str | None = option(
        help="what --design minimises instead, e.g. building:roi1:recall",
        group=DESIGN,
        needs="design",
    )
    design_budget: int = option(
        300,
        "candidates --design scores: the continuous searches' budget, the finest grid within "
        "it for the triangle and a lagrangian grid",
        type=whole_number(2),
        group=DESIGN,
        needs="design",
    )
    design_base: str | None = option(
        help="the matrix C0 of --design lagrangian (default robotistic; regional: a regional "
        "file too), the aggregate cost file of --design aggregate (default altruistic): a name "
        "or a .yaml",
        group=DESIGN,
        needs="design",
    )
    design_defer: list[float] | None = option(
        help="defer costs the designed matrix may take: a defer row in the space (the grid "
        "spaces: each; aggregate: the range from the smallest to the largest)",
        type=defer_cost,
        metavar="C",
        group=DESIGN,
        needs="design",
    )
    design_pixels: float = option(
        0.1,
        "share of each search image's labelled pixels that measures the objective in the "
        "search (seeded by --seed); the constraints are measured on every pixel that can "
        "change them, the certification on every pixel",
        type=share,
        group=DESIGN,
        needs="design",
    )

    monitor_require: list[str] | None = option(
        help="keep these requirements on the reported images as a stream of frames (in their "
        "order), e.g. 'person:roi1:recall>=0.8': one multiplier each, moved by each frame's "
        "loss when its labels arrive; the syntax of --require (recall or precision)",
        nargs="+",
        metavar="CONSTRAINT",
        group=MONITOR,
    )
    monitor_eta: float = option(
        0.5, "the step η of every --monitor_require multiplier", type=positive_number,
        group=MONITOR, needs="monitor_require",
    )  # fmt: skip
    monitor_scale: Literal["log", "mu"] = option(
        "log", "the scale θ of the multipliers: log (log(1 + μ)) or mu (μ itself)",
        group=MONITOR, needs="monitor_require",
    )  # fmt: skip
    monitor_delay: int = option(
        0, "frames until a frame's labels arrive (0: before the next frame)",
        type=whole_number(0), group=MONITOR, needs="monitor_require",
    )  # fmt: skip
    monitor_labelled: float = option(
        1.0, "share of the frames whose labels arrive at all (drawn with --seed)", type=share,
        group=MONITOR, needs="monitor_require",
    )  # fmt: skip
    monitor_start: str | None = option(
        help="a cost file of the monitor's space, e.g. a --design lagrangian's (with "
        "--monitor_space regional, a --design regional's) designed_cost.yaml: the multipliers "
        "start at its μ and it is the fixed matrix compared "
        "(default μ = 0: C0)",
        metavar="FILE",
        group=MONITOR,
        needs="monitor_require",
    )
    monitor_base: str = option(
        "robotistic", "the matrix C0 of the monitor's C(μ) = C0 + Σ μ_i A_i: a name or a .yaml",
        group=MONITOR, needs="monitor_require",
    )  # fmt: skip
    monitor_space: Literal["whole", "regional"] = option(
        "whole", "the monitor's matrices: whole (C0 + Σ μ_i A_i on every pixel) or regional "
        "(each requirement's μ moves only its RoI's matrix, roi0 every one: a stack decided with "
        "the RoI map)", group=MONITOR, needs="monitor_require",
    )  # fmt: skip
    monitor_max: float = option(
        100.0, "the cap μ_max of every multiplier (each frame's record serves μ in [0, μ_max])",
        type=positive_number, group=MONITOR, needs="monitor_require",
    )  # fmt: skip


def check_values(opts: Any) -> None:
    """ValueError naming the option when a field of ``opts`` holds a value its command line
    would refuse: the type, the choices, the number of values and the value type of its
    metadata. The command line's values pass here as the Python API's do
    (:func:`costseg.api.evaluate`), so every entry checks the same.

    >>> check_values(EvalOptions(conformal=1.5))
    Traceback (most recent call last):
    ValueError: --conformal: expected a number in (0, 1) such as 0.1, got '1.5'
    >>> check_values(EvalOptions(roi="geometrc"))
    Traceback (most recent call last):
    ValueError: --roi: expected one of priors, geometric; got 'geometrc'
    """
    hints = typing.get_type_hints(type(opts))
    for f in dataclasses.fields(opts):
        value = getattr(opts, f.name)
        if not f.init or (value is None and field_default(f) is None):
            continue
        try:
            _check_value(value, hints[f.name], f.metadata)
        except (ValueError, TypeError, argparse.ArgumentTypeError) as err:
            raise ValueError(f"{f.metadata.get('flag', f'--{f.name}')}: {err}") from None


def _check_value(value: Any, hint: Any, meta: Any) -> None:
    """Raise unless ``value`` is one the option of type ``hint`` and ``meta`` data accepts."""
    kinds = [a for a in typing.get_args(hint) if a is not type(None)]
    if typing.get_origin(hint) in (typing.Union, types.UnionType):
        hint = kinds[0]
    if typing.get_origin(hint) is list:
        if not isinstance(value, (list, tuple)):
            raise ValueError(f"expected a list of values, got {value!r}")
        count = meta.get("nargs")
        if isinstance(count, int) and len(value) != count:
            raise ValueError(f"expected {count} values, got {len(value)}")
        if count is None and not value:
            raise ValueError("expected at least one value")
        for item in value:
            _check_value(item, typing.get_args(hint)[0], meta)
    elif hint is bool:
        if not isinstance(value, bool):
            raise ValueError(f"expected True or False, got {value!r}")
    elif typing.get_origin(hint) is typing.Literal:
        choices = typing.get_args(hint)
        if value not in choices or isinstance(value, bool):
            raise ValueError(f"expected one of {', '.join(map(str, choices))}; got {value!r}")
    elif "type" in meta:
        meta["type"](str(value))
    elif hint in (int, float) and (isinstance(value, bool) or not isinstance(value, (int, float))):
        raise ValueError(f"expected a number, got {value!r}")
    elif hint is str and not isinstance(value, str):
        raise ValueError(f"expected a text, got {value!r}")


def check_needs(opts: Any) -> None:
    """ValueError when an option is given without the option it ``needs`` (its metadata: a
    field's name, or ``name=value`` with one value or several, ``name=a|b``).

    >>> check_needs(EvalOptions(conformal_sets="aps"))
    Traceback (most recent call last):
    ValueError: --conformal_sets goes with --conformal
    >>> check_needs(EvalOptions(conformal=0.1, conformal_tau=0.8))
    Traceback (most recent call last):
    ValueError: --conformal_tau goes with --conformal_loss binary
    """
    for f in dataclasses.fields(opts):
        name, _, value = f.metadata.get("needs", "").partition("=")
        if not name or not changed(opts, [f.name]):
            continue
        values = value.split("|") if value else []
        if (str(getattr(opts, name)) not in values) if values else not changed(opts, [name]):
            flag = changed(opts, [f.name])[0]
            raise ValueError(f"{flag} goes with --{name}" + (f" {' or '.join(values)}"
                                                              if values else ""))  # fmt: skip


def candidate_flags() -> str:
    """The flags whose rule groups ``--target`` and ``--guarantee`` choose among.

    >>> candidate_flags()
    '--sweep, --defer_sweep, --alpha_sweep, --fuse_tau'
    """
    fields = dataclasses.fields(EvalOptions)
    return ", ".join(f"--{f.name}" for f in fields if f.metadata.get("candidates"))


@dataclass
class PredictOptions(NetworkOptions):
    """Everything ``predict.py`` can be told (see ``python predict.py --help``)."""

    input: list[str] | None = option(
        help="images, folders of images (read with their sub-folders) and videos (need PyAV)",
        required=True,
        metavar="PATH",
    )
    meta_models: str | None = option(
        help="meta/models.joblib of an evaluate.py --meta run: each rule's segments coloured by "
        "their predicted IoU, one more row of the panels",
        metavar="PATH",
    )
    roi: Literal["priors", "geometric"] = same_option(SourceOptions, "roi")


@dataclass
class ExportOptions:
    """Everything ``scripts/export.py`` can be told: one network (evaluate.py's source options,
    one of them), the graph to write."""

    ckpt_path: list[str] | None = same_option(
        NetworkOptions, "ckpt_path", help="a costseg checkpoint (default: the newest)"
    )
    network: list[str] | None = same_option(
        NetworkOptions, "network", help="another source: vainf:PATH, hf:DIR, ..."
    )
    mc_dropout: int | None = same_option(
        NetworkOptions, "mc_dropout", help="refused: Monte-Carlo dropout has no single graph"
    )
    output: str | None = option(
        help="the graph to write (.onnx); FILE.json and FILE.priors.pt beside it",
        required=True,
        metavar="FILE",
    )
    probabilities: bool = option(False, "the graph also outputs the probabilities")
    regional: bool = option(
        False,
        "the graph takes a regional value system (docs/definitions.md §21): a stack of matrices, "
        "one per RoI, and the RoI map (uint8, resized to the image) as inputs",
    )
    overwrite: bool = same_option(
        NetworkOptions, "overwrite", help="replace an earlier export's files"
    )
