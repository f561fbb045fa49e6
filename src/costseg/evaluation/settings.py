"""Each analysis's settings: typed and frozen, resolved once from the options when the plan is
made (:data:`costseg.evaluation.analyses.ANALYSES` pairs each analysis with its resolver). An
analysis receives its settings and the evaluation's context, never the options.

A resolver returns None when the options do not ask for its analysis. No heavy imports: the
plan resolves settings before the network loads.

>>> from costseg.options import EvalOptions
>>> sweep_choice(EvalOptions(sweep=0.1, target=["person:roi1:recall>=0.9"],
...                          maximize="person:roi1:precision"))
SweepChoice(target='person:roi1:recall>=0.9', maximize='person:roi1:precision', delta=None, \
method='bonferroni')
>>> design_settings(EvalOptions()) is None
True
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from costseg.options import EvalOptions


@dataclass(frozen=True)
class Always:
    """The settings of an analysis that every evaluation runs and that takes no option."""


@dataclass(frozen=True)
class ScalingSettings:
    """``--calibrate``: the scaling fitted on the held-out images."""

    kind: Literal["temperature", "vector"]
    temperature_sweep: bool  # the named rules at the fitted T join the temperature sweep


@dataclass(frozen=True)
class SegmentSettings:
    """``--save-segments``, ``--meta``, ``--fuse``: segments and their meta models."""

    save: bool  # segments/<rule>.csv
    meta: bool  # meta models of the named rules, scored on the reported images
    num_examples: int  # the images whose segment maps are kept for the figures


@dataclass(frozen=True)
class SweepChoice:
    """``--target`` / ``--maximize`` (and ``--guarantee``): a point of the sweep, chosen on the
    reported images (best.json) and, with δ, certified on held-out images (Learn-then-Test)."""

    target: str
    maximize: str
    delta: float | None  # --guarantee
    method: Literal["bonferroni", "fixed_sequence"]


@dataclass(frozen=True)
class DesignSettings:
    """``--design``: a cost matrix designed from requirements (docs/definitions.md §20)."""

    space: Literal["triangle", "lagrangian", "aggregate", "regional"]
    search: Literal["grid", "continuous"] | None  # the multipliers' search (None: by the budget)
    requirements: tuple[str, ...]  # --require
    maximize: str | None
    minimize: str | None
    delta: float
    budget: int
    base: str | None
    defer: tuple[float, ...]
    pixels: float  # the share of each search image's labelled pixels scored for the objective
    seed: int  # of the D1 / D2 split, the objective's pixels and the continuous searches
    vertices: tuple[str, ...]  # the triangle's corners (the triangle is searched to compare)
    vertex_scaling: Literal["none", "mean"]
    held_out: str  # which images are held out, in words (the certificate names them)
    roi: Literal["priors", "geometric"]  # the RoI map the constraints' RoIs come from


@dataclass(frozen=True)
class MonitorSettings:
    """``--monitor_require``: requirements kept on the reported images as a stream
    (docs/definitions.md §22)."""

    requirements: tuple[str, ...]
    eta: float
    scale: Literal["log", "mu"]
    delay: int  # frames until a frame's labels arrive
    labelled: float  # the share of frames whose labels arrive
    start: str | None  # a cost file whose μ the multipliers start at (None: μ = 0)
    base: str  # C₀
    mu_max: float
    space: Literal["whole", "regional"]  # whole-image matrices or a stack by RoI
    seed: int  # of the labelled frames
    shift_onset: int  # the first shifted frame's position among the reported images (0: all)


@dataclass(frozen=True)
class SavedSettings:
    """``--save-probs`` / ``--save-predictions``."""

    probs: bool
    predictions: bool


@dataclass(frozen=True)
class ConformalSettings:
    """``--conformal`` and its loss (docs/definitions.md §18)."""

    alpha: float
    sets: Literal["lac", "aps"]
    loss: Literal["uniform", "cost", "binary"]
    tau: float  # the covered share of the binary loss
    roi: int | None  # count only this RoI's pixels


@dataclass(frozen=True)
class ExampleSettings:
    """The first reported images, shown in the mask figures (and the explorer)."""

    num_examples: int
    keep_probs: bool  # their float16 probabilities, for the explorer


@dataclass(frozen=True)
class ExplorerSettings:
    """``--explorer``: the triangle the page mixes and the defer cost of its rules."""

    vertices: tuple[str, ...]
    vertex_scaling: Literal["none", "mean"]
    defer: float | None


def always(opts: EvalOptions) -> Always:
    return Always()


def scaling_settings(opts: EvalOptions) -> ScalingSettings | None:
    if opts.calibrate is None:
        return None
    return ScalingSettings(opts.calibrate, opts.temperature_sweep)


def segment_settings(opts: EvalOptions) -> SegmentSettings | None:
    if not (opts.meta or opts.fuse or opts.save_segments):
        return None
    return SegmentSettings(opts.save_segments, opts.meta, opts.num_examples)


def sweep_choice(opts: EvalOptions) -> SweepChoice | None:
    """The sweep's choice; None without ``--target`` (the checks refuse what is incomplete)."""
    if not opts.target or opts.maximize is None:
        return None
    return SweepChoice(opts.target[0], opts.maximize, opts.guarantee, opts.guarantee_method)


def certified_choice(opts: EvalOptions) -> SweepChoice | None:
    """The sweep's choice certified with δ (``--guarantee``), else None."""
    choice = sweep_choice(opts)
    return choice if choice is not None and choice.delta is not None else None


def design_settings(opts: EvalOptions) -> DesignSettings | None:
    if opts.design is None:
        return None
    held_out = (
        f"--calibration_split {opts.calibration_split}"
        if opts.calibration_split is not None
        else f"the first half of --split {opts.split}"
        + ("" if opts.limit is None else f" (of its first {opts.limit} images)")
    )
    return DesignSettings(
        space=opts.design,
        search=opts.design_search,
        requirements=tuple(opts.require or ()),
        maximize=opts.design_maximize,
        minimize=opts.design_minimize,
        delta=opts.design_delta,
        budget=opts.design_budget,
        base=opts.design_base,
        defer=tuple(opts.design_defer or ()),
        pixels=opts.design_pixels,
        seed=opts.seed,
        vertices=tuple(opts.vertices),
        vertex_scaling=opts.vertex_scaling,
        held_out=held_out,
        roi=opts.roi,
    )


def monitor_settings(opts: EvalOptions) -> MonitorSettings | None:
    if not opts.monitor_require:
        return None
    return MonitorSettings(
        requirements=tuple(opts.monitor_require),
        eta=opts.monitor_eta,
        scale=opts.monitor_scale,
        delay=opts.monitor_delay,
        labelled=opts.monitor_labelled,
        start=opts.monitor_start,
        base=opts.monitor_base,
        mu_max=opts.monitor_max,
        space=opts.monitor_space,
        seed=opts.seed,
        shift_onset=opts.shift_onset or 0,
    )


def saved_settings(opts: EvalOptions) -> SavedSettings | None:
    if not (opts.save_probs or opts.save_predictions):
        return None
    return SavedSettings(opts.save_probs, opts.save_predictions)


def anomaly_settings(opts: EvalOptions) -> ExampleSettings | None:
    return ExampleSettings(opts.num_examples, keep_probs=False) if opts.anomalies else None


def conformal_settings(opts: EvalOptions) -> ConformalSettings | None:
    if opts.conformal is None:
        return None
    return ConformalSettings(
        opts.conformal, opts.conformal_sets, opts.conformal_loss, opts.conformal_tau,
        opts.conformal_roi,
    )  # fmt: skip


def example_settings(opts: EvalOptions) -> ExampleSettings:
    return ExampleSettings(opts.num_examples, keep_probs=opts.explorer)


def explorer_settings(opts: EvalOptions) -> ExplorerSettings | None:
    if not opts.explorer:
        return None
    return ExplorerSettings(tuple(opts.vertices), opts.vertex_scaling, opts.defer)
