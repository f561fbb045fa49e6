"""The analyses of an evaluation: one module per capability, all in :data:`ANALYSES`.

The loop (:mod:`costseg.evaluation.loop`) knows none of them by name. The plan resolves each
wanted analysis's settings once (:mod:`costseg.evaluation.settings`); the loop opens the
analyses (importing only their modules), lets each :meth:`Analysis.fit` on the held-out images
(kept from their one pass through the network) in the order their declared dependencies give,
applies what each fit provides (:class:`Provided`), freezes the rule groups, shows each analysis
every reported batch as a :class:`Seen` (:meth:`Analysis.process`), and collects their typed
results (:class:`~costseg.report.sections.Result`), each of which writes its own files and
returns its share of the shared outputs (results.json keys, a table.md section, figures as
picklable jobs, TensorBoard). A new capability is its module here, its settings in
:mod:`costseg.evaluation.settings` (with its options in :mod:`costseg.options`), its result in
:mod:`costseg.report` and one :class:`Entry` below.

>>> from costseg.options import EvalOptions
>>> [e.module for e, _ in wanted(EvalOptions(calibrate="temperature"))][:2]
['scaling', 'metrics']
"""

from __future__ import annotations

import importlib
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from functools import cached_property
from typing import TYPE_CHECKING, Any

from costseg.evaluation.settings import (
    always,
    anomaly_settings,
    certified_choice,
    conformal_settings,
    design_settings,
    example_settings,
    explorer_settings,
    monitor_settings,
    saved_settings,
    scaling_settings,
    segment_settings,
    sweep_choice,
)

if TYPE_CHECKING:
    import torch

    from costseg.calibration.scaling import Scaling
    from costseg.evaluation.held_out import HeldOut
    from costseg.networks.sources import Batch
    from costseg.options import EvalOptions
    from costseg.report.early_figures import EarlyFigures
    from costseg.report.sections import Result
    from costseg.rules import RuleGroup


@dataclass(frozen=True)
class Entry:
    """One analysis: its module (``costseg.evaluation.analyses.<module>``, which defines
    ``ANALYSIS``, an :class:`Analysis` subclass), the resolver of its settings (None: the
    options do not ask for it), the results.json keys it leaves null when not run, the flag
    that asks for it where it fits on held-out images (``--calibration_split``, or the first
    half of ``--split``), the analyses whose fits must come before its own (it sees what
    they provide: the scaled probabilities, the fused rules' meta models), and the report
    modules of the figures its result draws (the figure workers import them once, at start)."""

    module: str
    settings: Callable[[EvalOptions], Any]
    absent: tuple[str, ...] = ()
    held_out: str | None = None
    after: tuple[str, ...] = ()
    figures: tuple[str, ...] = ()


ANALYSES: tuple[Entry, ...] = (
    Entry("scaling", scaling_settings, held_out="--calibrate"),
    Entry(
        "metrics",
        always,
        figures=("figures", "priors", "cost_matrix", "ternary", "curves"),
    ),
    Entry(
        "segments",
        segment_settings,
        absent=("meta",),
        after=("scaling",),
        figures=("segment_figures",),
    ),
    Entry("choice", sweep_choice),
    Entry("guarantee", certified_choice, held_out="--guarantee", after=("scaling", "segments")),
    Entry(
        "design",
        design_settings,
        absent=("design",),
        held_out="--design",
        after=("scaling",),
        figures=("design_figures",),
    ),
    Entry("calibration", always, figures=("curves",)),
    Entry("saved", saved_settings),
    Entry("anomalies", anomaly_settings, absent=("anomalies",), figures=("anomaly_figures",)),
    Entry(
        "conformal",
        conformal_settings,
        absent=("conformal",),
        held_out="--conformal",
        after=("scaling",),
        figures=("conformal",),
    ),
    Entry("monitor", monitor_settings, absent=("monitor",), figures=("monitor_figures",)),
    Entry("examples", example_settings, figures=("uncertainty",)),
    Entry("explorer", explorer_settings),
)


def wanted(opts: EvalOptions) -> list[tuple[Entry, Any]]:
    """The entries of :data:`ANALYSES` that ``opts`` ask for, each with its settings."""
    resolved = ((entry, entry.settings(opts)) for entry in ANALYSES)
    return [(entry, settings) for entry, settings in resolved if settings is not None]


def fit_order(entries: Sequence[Entry]) -> list[Entry]:
    """``entries`` in an order in which each fits after those it names in ``after`` (the table's
    order among the rest); ValueError for a dependency on no analysis or a cycle.

    >>> [e.module for e in fit_order([ANALYSES[3 + 1], ANALYSES[2], ANALYSES[0]])]
    ['scaling', 'segments', 'guarantee']
    """
    known = {e.module for e in ANALYSES}
    for entry in entries:
        if unknown := set(entry.after) - known:
            raise ValueError(f"analysis {entry.module} fits after unknown {sorted(unknown)}")
    ordered: list[Entry] = []
    waiting = list(entries)
    while waiting:
        present = {e.module for e in waiting}
        ready = [e for e in waiting if not present & set(e.after)]
        if not ready:
            raise ValueError(f"analyses that wait on each other: {sorted(present)}")
        ordered.append(ready[0])
        waiting.remove(ready[0])
    return ordered


def held_out_flags(opts: EvalOptions | None = None) -> list[str]:
    """The flags of the analyses that fit on held-out images (those ``opts`` ask for)."""
    return [
        e.held_out
        for e in ANALYSES
        if e.held_out and (opts is None or e.settings(opts) is not None)
    ]


def null_keys(ran: dict[Entry, Result | None]) -> tuple[str, ...]:
    """The results.json keys of the analyses that did not run or found nothing to write (null,
    so every results.json has them); ``ran``: each wanted entry's result."""
    return tuple(key for e in ANALYSES if ran.get(e) is None for key in e.absent)


def figure_modules(entries: Sequence[Entry]) -> list[str]:
    """The report modules (``costseg.report.<name>``) of the figures ``entries`` draw.

    >>> figure_modules([e for e in ANALYSES if e.module == "design"])
    ['costseg.report.design_figures']
    """
    names = dict.fromkeys(name for entry in entries for name in entry.figures)
    return [f"costseg.report.{name}" for name in names]


def analysis_class(entry: Entry) -> type[Analysis]:
    """The class of ``entry`` (its module imported now, and only when wanted)."""
    return importlib.import_module(f"{__name__}.{entry.module}").ANALYSIS


def import_analyses(entries: Sequence[Entry]) -> None:
    """Import the modules of ``entries`` (and what they import)."""
    for entry in entries:
        analysis_class(entry)


@dataclass(frozen=True)
class Provided:
    """What a fit hands on to the analyses after it (the loop applies it): the fitted scaling
    of the probabilities, rule groups that join the evaluation (the named rules at a fitted
    temperature, the designed matrices), and rule groups that replace the plan's group of the
    same family (the fused rules with their meta models)."""

    scaling: Scaling | None = None
    groups: tuple[RuleGroup, ...] = ()
    replaced: tuple[RuleGroup, ...] = ()


class Decisions(Sequence):
    """Every rule group's (B, K, H, W) label maps of one batch, each decided on first use and
    kept: an analysis of the held-out images asks only for the groups it needs, and every group
    decides on the probabilities of its temperature (the main ones when None)."""

    def __init__(self, seen: Seen) -> None:
        self.seen, self.maps = seen, {}

    def __len__(self) -> int:
        return len(self.seen.context.groups)

    def __getitem__(self, index: int) -> torch.Tensor:
        if index not in self.maps:
            group, seen = self.seen.context.groups[index], self.seen
            self.maps[index] = group.decide(seen.tempered(group.temperature), seen.priors, seen.roi)
        return self.maps[index]


@dataclass(eq=False)
class Seen:
    """One batch of images as every analysis sees it, reported or held out
    (:meth:`Context.see`, the one step from scores to decisions).

    Attributes:
        batch: images, labels, instance ids, anomaly masks, names and the source's scores.
        probs: (B, N, H, W) the probabilities every rule group decides on (scaled; rounded to
            float16 with ``--save-probs`` for the reported images, as saved).
        priors, roi: the pixel-wise priors and (H, W) RoI ids at the labels' size, or None.
        unrounded: ``probs`` before the float16 rounding (the same tensor without it).
        context: the evaluation's shared state (the plan, the fitted scaling, the groups).
        positions: each image's position among all reported images (the order of one process,
            whichever process sees it); None for held-out images.
    """

    batch: Batch
    probs: torch.Tensor
    priors: torch.Tensor | None
    roi: torch.Tensor | None
    unrounded: torch.Tensor
    context: Context
    positions: list[int] | None = None

    @cached_property
    def preds(self) -> Decisions:
        """Per rule group of ``context.groups`` (in its order), the (B, K, H, W) label maps."""
        return Decisions(self)

    def tempered(self, temperature: float | None) -> torch.Tensor:
        """The probabilities a group of ``temperature`` decides on: ``probs``, or the raw
        logits' softmax at T."""
        from costseg.calibration.scaling import Scaling

        if temperature is None:
            return self.probs
        logits = self.context.plan.source.logits_of(self.batch.scores)
        return Scaling("temperature", temperature=temperature).apply(logits)

    @cached_property
    def unscaled(self) -> torch.Tensor:
        """The source's probabilities before the scaling (``probs`` when there is none)."""
        if self.context.scaling.kind == "none":
            return self.probs
        return self.context.plan.source.probabilities_of(self.batch.scores)

    @cached_property
    def uncertainty(self) -> dict[str, torch.Tensor]:
        """The (B, H, W) uncertainty maps of the unscaled, unrounded probabilities
        (docs/definitions.md §13)."""
        from costseg.networks.uncertainty import output_maps

        probs = self.unrounded if self.context.scaling.kind == "none" else self.unscaled
        return output_maps(probs, self.batch.expected_entropy)

    @property
    def named(self) -> torch.Tensor:
        """(B, K, H, W) the named rules' label maps."""
        return self.preds[self.context.named]


@dataclass(eq=False)
class Context:
    """What the analyses of one evaluation share: the plan (read, never changed), the fitted
    scaling, the rule groups (the plan's, then what fits provide; a tuple, frozen, once every
    fit is done), the held-out images (one pass of the network, kept) and the figures drawn
    early."""

    plan: Any  # the EvalPlan (evaluation/plan.py, which imports this module's table)
    scaling: Scaling
    held_out: HeldOut | None = None  # the calibration images
    meta_held_out: HeldOut | None = None  # the meta models' images (often the same object)
    early: EarlyFigures | None = None  # figures drawn while the images are evaluated

    def __post_init__(self) -> None:
        self.groups: list[RuleGroup] | tuple[RuleGroup, ...] = list(self.plan.groups)

    def apply(self, provided: Provided | None) -> None:
        """Take on what a fit provides (:class:`Provided`)."""
        if provided is None:
            return
        if provided.scaling is not None:
            self.scaling = provided.scaling
        families = {g.family: g for g in provided.replaced}
        self.groups = [families.get(g.family, g) for g in self.groups] + list(provided.groups)

    def freeze(self) -> None:
        """Every fit is done: the rule groups of the reported images, fixed from now on."""
        self.groups = tuple(self.groups)

    @property
    def named(self) -> int:
        """The index of the named rules' group in ``groups``."""
        return next(i for i, g in enumerate(self.groups) if g.is_named)

    def probabilities(self, batch: Batch) -> torch.Tensor:
        """The probabilities the rules see for ``batch``: the source's, scaled."""
        source = self.plan.source
        if self.scaling.kind != "none":
            return self.scaling.apply(source.logits_of(batch.scores))
        return source.probabilities_of(batch.scores)

    def see(self, batch: Batch, positions: list[int] | None = None) -> Seen:
        """The one step from a batch's scores to what the analyses see: its probabilities
        (for reported images with ``--save-probs``, rounded to float16 as saved), priors, RoIs
        and every group's decisions (each on first use)."""
        unrounded = self.probabilities(batch)
        rounded = positions is not None and self.plan.round_probs
        probs = unrounded.half().float() if rounded else unrounded
        priors, roi = self.plan.priors.at(tuple(batch.labels.shape[-2:]))
        return Seen(batch, probs, priors, roi, unrounded, self, positions)

    def held_out_seen(self, what: str, held: HeldOut | None = None) -> Iterator[Seen]:
        """The held-out images (``held``; default the calibration images) seen batch by batch
        as the reported ones are (a progress bar named ``what``)."""
        for batch in (held or self.held_out).batches(what):
            yield self.see(batch)


class Analysis:
    """One capability of an evaluation. Subclasses override what they need.

    Construction (with the analysis's settings, :mod:`costseg.evaluation.settings`) happens
    after every option check and before the held-out images are seen; :meth:`fit` runs after
    the fits of the analyses its entry names in ``after`` (seeing held-out images through
    :meth:`Context.held_out_seen`, the one step from scores to decisions) and returns what it
    provides to the later ones, never changing the plan or the context itself; then
    :meth:`start`, then :meth:`process` for each reported batch (this process's share under
    ``torchrun``), :meth:`gather` and :meth:`result` once at the end.
    """

    def __init__(self, settings: Any, context: Context) -> None:
        self.settings = settings
        self.context = context

    every_entropy: bool = False
    """Whether :meth:`process` needs the expected entropy of a source of several runs on every
    reported image (else on the first ``--num_examples``: each costs a pass per run)."""

    def fit(self) -> Provided | None:
        """Learn from the held-out images; what this provides to the later analyses."""
        return None

    def start(self) -> None:
        """Every fit is done: set up what :meth:`process` accumulates."""

    def process(self, seen: Seen) -> None:
        """See one reported batch."""

    def gather(self) -> None:
        """After the last reported batch, before :meth:`result`: bring every process's share of
        the reported images together (under ``torchrun``) with the collectives of
        :mod:`costseg.evaluation.processes`: per-image records into the reported images' order
        (``in_image_order``), other counts into their sum (``summed``). torchmetrics states
        need nothing here: they sum themselves across processes."""

    def result(self) -> Result | None:
        """The typed result (None: nothing to write)."""
        return None


__all__ = [
    "ANALYSES",
    "Analysis",
    "Context",
    "Decisions",
    "Entry",
    "Provided",
    "Seen",
    "analysis_class",
    "figure_modules",
    "fit_order",
    "held_out_flags",
    "import_analyses",
    "null_keys",
    "wanted",
]
