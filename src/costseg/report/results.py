"""What an evaluation produces, as typed values: per rule group its metrics and flat rows, the
examples, and the result of every analysis (:mod:`costseg.evaluation.analyses` fills them; each
writes its own outputs). Nothing here knows the model, the data loading or Lightning.
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TypeVar

import torch

from costseg.classes import CLASS_NAMES, ROI_NAMES
from costseg.metrics.names import (
    DEFER_RATES,
    DEFER_RULE_RATES,
    INSTANCE_COLUMNS,
    PIXEL_RATES,
    RULE_RATES,
    SEGMENT_COUNTS,
    SEGMENT_RATES,
    segment_column,
)
from costseg.rules import RuleGroup

ROIS = tuple(range(len(ROI_NAMES)))


@dataclass
class GroupResult:
    """One rule group's metrics: ``RoIPrecisionRecall.compute()``, ``SegmentErrors.compute()``
    and ``InstanceMisses.compute()`` (see :mod:`costseg.metrics`; empty when not measured), plus
    per-image counts when a guarantee needs them."""

    group: RuleGroup
    pixels: dict[str, torch.Tensor]
    segments: dict[str, torch.Tensor]
    per_image: dict[str, torch.Tensor] = field(default_factory=dict)
    instances: dict[str, torch.Tensor] = field(default_factory=dict)

    def __post_init__(self) -> None:  # the metrics' sums may be on a GPU
        self.pixels, self.segments = on_cpu(self.pixels), on_cpu(self.segments)
        self.per_image, self.instances = on_cpu(self.per_image), on_cpu(self.instances)

    def rows(self, class_ids: Sequence[int], rois: Sequence[int] = ROIS) -> list[dict]:
        """One row per rule × class × RoI: the columns of
        :data:`~costseg.metrics.names.ROW_METRICS` (segment ones only where measured, those of
        deferral only where a rule of the group defers).

        The rule is identified by the group's columns (``matrix``, and ``defer`` where a rule
        defers; ``alpha, beta, gamma``; or ``prior_alpha``). NaN marks an undefined ratio.
        """
        rows = []
        for k, columns in enumerate(self.group.columns):
            for c, cls in enumerate(class_ids):
                for r in rois:
                    row = {**columns, "class": CLASS_NAMES[cls], "roi": r}
                    row |= {m: self.pixels[m][k, r, cls].item() for m in PIXEL_RATES}
                    row |= self._defer_columns(k, cls, r)
                    row |= self._segment_columns(k, c, r)
                    row |= self._instance_columns(k, cls, r)
                    row |= {m: self.pixels[m][k].item() for m in RULE_RATES}
                    rows.append(row)
        return rows

    def _defer_columns(self, k: int, cls: int, r: int) -> dict:
        """Deferral of rule k, class ``cls``, RoI r (none unless a rule of the group defers)."""
        if not self.group.defers:
            return {}
        rates = {m: self.pixels[m][k, r, cls].item() for m in DEFER_RATES}
        return rates | {m: self.pixels[m][k, r].item() for m in DEFER_RULE_RATES}

    def _segment_columns(self, k: int, c: int, r: int) -> dict:
        """Segment counts and rates of rule k, class position c, RoI r (none if not measured)."""
        if not self.segments:
            return {}
        seg = self.segments
        counts = {segment_column(m): int(seg[m][k, c, r]) for m in SEGMENT_COUNTS}
        return counts | {m: seg[m][k, c, r].item() for m in SEGMENT_RATES}

    def _instance_columns(self, k: int, cls: int, r: int) -> dict:
        """Instances of rule k, class ``cls``, RoI r (none if not measured for the class)."""
        classes = self.instances.get("classes", torch.zeros(0)).tolist()
        if cls not in classes:
            return {}
        c = classes.index(cls)
        return {key: self.instances[key][k, c, r].item() for key in INSTANCE_COLUMNS}


@dataclass
class Example:
    """One image of the mask figures: (3, H, W) uint8, (H, W) labels, (K, H, W) named-rule maps;
    for the explorer page its name and (N, H, W) float16 probabilities; its (H, W) float16
    uncertainty maps (docs/definitions.md §13)."""

    image: torch.Tensor
    label: torch.Tensor
    preds: torch.Tensor
    name: str = ""
    probs: torch.Tensor | None = None
    uncertainty: dict[str, torch.Tensor] = field(default_factory=dict)


@dataclass
class GroupResults:
    """The metrics of every rule group (:class:`GroupResult`, in the plan's order) and the line
    saying which classes' instances were measured."""

    groups: list[GroupResult]
    instances: str = ""


@dataclass
class Examples:
    """The images of the mask figures and the explorer."""

    examples: list[Example]


R = TypeVar("R")


@dataclass
class EvalResults:
    """Everything the report needs about one evaluation, on the CPU (its figures are drawn in
    worker processes from NumPy copies; see :mod:`costseg.report.drawing`).

    Attributes:
        output_dir: where the outputs go.
        options_record: the options as given, for results.json (read by no report).
        source: what produced the probabilities (network, checkpoint or folder).
        probabilities: which probabilities were used (raw, or the scaling and its parameters).
        class_ids: classes of the segment metrics and tables.
        rois: the RoIs a target or requirement names, shown beside the paper's in the tables.
        roi: (H, W) RoI map at label resolution, if priors exist.
        num_images: images evaluated.
        analyses: the typed result of every analysis that ran, in the analyses' order
            (:mod:`costseg.evaluation.analyses`); each writes its own outputs.
        null_keys: the results.json keys of the analyses that did not run (written as null).
        shifts: the shift the images were seen through (one at most; ``--shift``).
    """

    output_dir: Path
    options_record: dict
    source: dict
    probabilities: str
    class_ids: list[int]
    rois: tuple[int, ...] = ()
    roi: torch.Tensor | None = None
    num_images: int = 0
    analyses: list = field(default_factory=list)
    null_keys: tuple[str, ...] = ()
    shifts: list[str] = field(default_factory=list)

    def find(self, kind: type[R]) -> R | None:
        """The result of type ``kind``, or None when that analysis did not run."""
        return next((r for r in self.analyses if isinstance(r, kind)), None)

    @property
    def groups(self) -> list[GroupResult]:
        """Every rule group's result."""
        return self.find(GroupResults).groups

    @property
    def examples(self) -> list[Example]:
        """The examples of the mask figures (none when no analysis kept any)."""
        kept = self.find(Examples)
        return kept.examples if kept else []

    @property
    def named(self) -> GroupResult:
        """The result of the named rules (``--cost``)."""
        return next(g for g in self.groups if g.group.is_named)

    @property
    def design(self):
        """The outcome of ``--design`` (:class:`costseg.report.design.DesignOutcome`: the
        requirements, the split, each searched space and its chosen matrix), or None."""
        # by name: report/design.py imports this module
        return next((r for r in self.analyses if type(r).__name__ == "DesignOutcome"), None)

    @property
    def subject(self) -> str:
        """What every figure of this evaluation shows, for its title (:func:`figure_subject`)."""
        return figure_subject(self.source, self.shifts)

    def result_of(self, group: RuleGroup) -> GroupResult:
        """The result of ``group`` (the same family and rules)."""
        same = (group.family, group.names)
        return next(g for g in self.groups if (g.group.family, g.group.names) == same)


def figure_subject(source: dict, shifts: Sequence[str]) -> str:
    """The network (or the folder of saved probabilities) and the shifts the images were seen
    through, for the titles of an evaluation's figures.

    >>> checkpoint = "costseg:/x/runs/toy/version_0/checkpoints/last.ckpt"
    >>> figure_subject({"network": checkpoint}, ["fog:3"])
    'costseg:toy/version_0, images seen through fog:3'
    """
    source_name = str(source.get("network") or source.get("probs") or "")
    names = re.sub(r"[^\s:?+]*/[^\s?+]*", lambda m: _short_path(m.group()), source_name)
    return ", ".join([names] * bool(names) + [f"images seen through {s}" for s in shifts])


def _short_path(path: str) -> str:
    """A checkpoint ``.../<run>/version_<n>/checkpoints/<file>`` as ``<run>/version_<n>``,
    any other path as its last part."""
    parts = Path(path).parts
    if len(parts) >= 4 and parts[-2] == "checkpoints":
        return f"{parts[-4]}/{parts[-3]}"
    return parts[-1] if parts else path


def on_cpu(value):
    """``value`` with every tensor in it (in dicts and lists) on the CPU."""
    if isinstance(value, torch.Tensor):
        return value.cpu()
    if isinstance(value, dict):
        return {k: on_cpu(v) for k, v in value.items()}
    if isinstance(value, list):
        return [on_cpu(v) for v in value]
    return value
