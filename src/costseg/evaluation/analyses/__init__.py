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
from collections.abc import Callable
from dataclasses import dataclass
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
    Entry("guarantee", lambda o: o.guarantee is not None, held_out="--guarantee"),
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


@dataclass(eq=False)
class Seen:
    """One reported batch as every analysis sees it.

    Attributes:
        batch: images, labels, instance ids, anomaly masks, names and the source's scores.
        probs: (B, N, H, W) the probabilities every rule group decided on (scaled; rounded to
            float16 with ``--save-probs``, as saved).
        preds: per rule group of the plan (in its order), the (B, K, H, W) label maps.
        priors, roi: the pixel-wise priors and (H, W) RoI ids at the labels' size, or None.
        unrounded: ``probs`` before the float16 rounding (the same tensor without it).
        context: the evaluation's shared state (the plan, the fitted scaling).
    """

    batch: Batch
    probs: torch.Tensor
    preds: list[torch.Tensor]
    priors: torch.Tensor | None
    roi: torch.Tensor | None
    unrounded: torch.Tensor
    context: Context

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
    """What the analyses of one evaluation share: the plan, the fitted scaling, the held-out
    images (one pass of the network, kept), and the results written so far."""

    plan: Any  # the EvalPlan (evaluation/plan.py, which imports this module's checks)
    scaling: Scaling
    held_out: HeldOut | None = None  # the calibration images
    meta_held_out: HeldOut | None = None  # the meta models' images (often the same object)
    early: EarlyFigures | None = None  # figures drawn while the images are evaluated

    @property
    def named(self) -> int:
        """The index of the named rules' group in ``plan.groups``."""
        return next(i for i, g in enumerate(self.plan.groups) if g.is_named)

    def probabilities(self, batch: Batch) -> torch.Tensor:
        """The probabilities the rules see for ``batch``: the source's, scaled."""
        source = self.plan.source
        if self.scaling.kind != "none":
            return self.scaling.apply(source.logits_of(batch.scores))
        return source.probabilities_of(batch.scores)


class Analysis:
    """One capability of an evaluation. Subclasses override what they need.

    Construction happens after every option check and before the held-out images are seen;
    :meth:`fit` runs in :data:`ANALYSES`' order, then :meth:`start`, then :meth:`process` for
    each reported batch, and :meth:`result` once at the end.
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

    def result(self) -> Result | None:
        """The typed result (None: nothing to write)."""
        return None


__all__ = [
    "ANALYSES",
    "Analysis",
    "Context",
    "Entry",
    "Seen",
    "analysis_class",
    "held_out_flags",
    "import_analyses",
    "null_keys",
    "wanted",
]
