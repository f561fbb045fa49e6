"""The analyses of an evaluation: one module per capability, all in :data:`ANALYSES`.

The loop (:mod:`costseg.evaluation.loop`) knows none of them by name. It opens the analyses the
options ask for (importing only their modules), lets each :meth:`Analysis.fit` on the held-out
images (kept from their one pass through the network), shows each one every reported batch as a
:class:`Seen` (:meth:`Analysis.process`), and collects their typed results
(:class:`~costseg.report.sections.Result`), each of which writes its own files and returns its
share of the shared outputs (results.json keys, a table.md section, figures as picklable jobs,
TensorBoard). A new capability is its module here, its result in :mod:`costseg.report`, its
options in :mod:`costseg.options` and one :class:`Entry` below.

>>> from costseg.options import EvalOptions
>>> [e.module for e in wanted(EvalOptions(calibrate="temperature"))][:2]
['scaling', 'metrics']
"""

from __future__ import annotations

import importlib
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from functools import cached_property
from typing import TYPE_CHECKING, Any

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
    ``ANALYSIS``, an :class:`Analysis` subclass), when the options want it, the results.json
    keys it leaves null when not run, and the flag that asks for it where it fits on held-out
    images (``--calibration_split``, or the first half of ``--split``)."""

    module: str
    wanted: Callable[[EvalOptions], bool]
    absent: tuple[str, ...] = ()
    held_out: str | None = None


def _always(opts: EvalOptions) -> bool:
    return True


ANALYSES: tuple[Entry, ...] = (
    # fit order: the scaling changes the probabilities every later analysis sees; the meta
    # models decide the fused rules the guarantee may certify
    Entry("scaling", lambda o: o.calibrate is not None, held_out="--calibrate"),
    Entry("metrics", _always),
    Entry("segments", lambda o: bool(o.meta or o.fuse or o.save_segments), absent=("meta",)),
    Entry("guarantee", lambda o: o.guarantee is not None and not o.design, held_out="--guarantee"),
    Entry("design", lambda o: o.design is not None, absent=("design",), held_out="--design"),
    Entry("calibration", _always),
    Entry("saved", lambda o: bool(o.save_probs or o.save_predictions)),
    Entry("anomalies", lambda o: o.anomalies, absent=("anomalies",)),
    Entry(
        "conformal",
        lambda o: o.conformal is not None,
        absent=("conformal",),
        held_out="--conformal",
    ),
    Entry("examples", _always),
    Entry("explorer", lambda o: o.explorer),
)


def wanted(opts: EvalOptions) -> list[Entry]:
    """The entries of :data:`ANALYSES` that ``opts`` ask for, in the table's order."""
    return [entry for entry in ANALYSES if entry.wanted(opts)]


def held_out_flags(opts: EvalOptions | None = None) -> list[str]:
    """The flags of the analyses that fit on held-out images (those ``opts`` ask for)."""
    return [e.held_out for e in ANALYSES if e.held_out and (opts is None or e.wanted(opts))]


def null_keys(ran: dict[Entry, Result | None]) -> tuple[str, ...]:
    """The results.json keys of the analyses that did not run or found nothing to write (null,
    so every results.json has them); ``ran``: each wanted entry's result."""
    return tuple(key for e in ANALYSES if ran.get(e) is None for key in e.absent)


def analysis_class(entry: Entry) -> type[Analysis]:
    """The class of ``entry`` (its module imported now, and only when wanted)."""
    return importlib.import_module(f"{__name__}.{entry.module}").ANALYSIS


def import_analyses(opts: EvalOptions) -> None:
    """Import the modules of the wanted analyses (and what they import)."""
    for entry in wanted(opts):
        analysis_class(entry)


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
            group = self.seen.context.groups[index]
            self.maps[index] = group.decide(self.seen.tempered(group.temperature), self.seen.priors)
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
    scaling, the rule groups (the plan's, then what a fit hands on: the named rules at a fitted
    temperature, the fused rules with their meta models), the held-out images (one pass of the
    network, kept) and the figures drawn early."""

    plan: Any  # the EvalPlan (evaluation/plan.py, which imports this module's checks)
    scaling: Scaling
    held_out: HeldOut | None = None  # the calibration images
    meta_held_out: HeldOut | None = None  # the meta models' images (often the same object)
    early: EarlyFigures | None = None  # figures drawn while the images are evaluated
    groups: list[RuleGroup] = field(default_factory=list)

    def __post_init__(self) -> None:
        self.groups = self.groups or list(self.plan.groups)

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
        rounded = positions is not None and self.plan.options.save_probs
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

    Construction happens after every option check and before the held-out images are seen;
    :meth:`fit` runs in :data:`ANALYSES`' order (seeing the held-out images through
    :meth:`Context.held_out_seen`, and handing what it fitted on through the context, never by
    changing the plan), then :meth:`start`, then :meth:`process` for each reported batch (this
    process's share under ``torchrun``), :meth:`gather` and :meth:`result` once at the end.
    """

    def __init__(self, context: Context) -> None:
        self.context = context
        self.opts = context.plan.options

    every_entropy: bool = False
    """Whether :meth:`process` needs the expected entropy of a source of several runs on every
    reported image (else on the first ``--num_examples``: each costs a pass per run)."""

    def fit(self) -> None:
        """Learn from the held-out images (``self.context.held_out``)."""

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
    "Seen",
    "analysis_class",
    "held_out_flags",
    "import_analyses",
    "null_keys",
    "wanted",
]
