"""What an evaluation produces, as typed values: per rule group its metrics, and flat rows.

The job (:mod:`costseg.evaluation`) fills these; :mod:`costseg.report` writes them. Nothing here
knows the model, the data loading or Lightning.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import torch

from costseg.classes import CLASS_NAMES
from costseg.rules import RuleGroup

ROIS = (0, 1, 2, 3, 4)
INSTANCE_COLUMNS = (
    "gt_instances",
    "missed_instances",
    "instance_recall",
    "missed_small",
    "missed_medium",
    "missed_large",
)
"""The instance metrics of each row (``docs/definitions.md §9``), where measured."""


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

    def rows(self, class_ids: Sequence[int], rois: Sequence[int] = ROIS) -> list[dict]:
        """One row per rule × class × RoI: precision, recall, segment counts and rates, mIoU.

        The rule is identified by the group's columns (``matrix``; ``alpha, beta, gamma``; or
        ``prior_alpha``). NaN marks an undefined ratio.
        """
        pixels = self.pixels
        rows = []
        for k, columns in enumerate(self.group.columns):
            for c, cls in enumerate(class_ids):
                for r in rois:
                    rows.append(
                        {
                            **columns,
                            "class": CLASS_NAMES[cls],
                            "roi": r,
                            "precision": pixels["precision"][k, r, cls].item(),
                            "recall": pixels["recall"][k, r, cls].item(),
                            **self._segment_columns(k, c, r),
                            **self._instance_columns(k, cls, r),
                            "miou": pixels["miou"][k].item(),
                        }
                    )
        return rows

    def _segment_columns(self, k: int, c: int, r: int) -> dict:
        """Segment counts and rates of rule k, class position c, RoI r (none if not measured)."""
        if not self.segments:
            return {}
        seg = self.segments
        counts = {f"{key}_segments": int(seg[key][k, c, r]) for key in ("fp", "fn")}
        totals = {f"{key}_segments": int(seg[key][k, c, r]) for key in ("n_pred", "n_gt")}
        rates = {key: seg[key][k, c, r].item() for key in ("fp_rate", "fn_rate")}
        return counts | totals | rates

    def _instance_columns(self, k: int, cls: int, r: int) -> dict:
        """Instances of rule k, class ``cls``, RoI r (none if not measured for the class)."""
        classes = self.instances.get("classes", torch.zeros(0)).tolist()
        if cls not in classes:
            return {}
        c = classes.index(cls)
        return {key: self.instances[key][k, c, r].item() for key in INSTANCE_COLUMNS}


@dataclass
class Example:
    """One image of the mask figures: (3, H, W) uint8, (H, W) labels, (K, H, W) named-rule maps."""

    image: torch.Tensor
    label: torch.Tensor
    preds: torch.Tensor


@dataclass
class EvalResults:
    """Everything the report needs about one evaluation, on the CPU (the report draws on forked
    processes, which cannot use CUDA; see :mod:`costseg.report.drawing`).

    Attributes:
        output_dir: where the outputs go.
        options: the options as given (for the JSON record).
        source: what produced the probabilities (network, checkpoint or folder).
        probabilities: which probabilities were used (raw, or the scaling and its parameters).
        class_ids: classes of the segment metrics and tables.
        groups: one result per rule group; the named rules come first.
        examples: images for the mask figures.
        roi: (H, W) RoI map at label resolution, if priors exist.
        num_images: images evaluated.
        extra: results of optional analyses (calibration, temperature sweep, guarantee).
    """

    output_dir: Path
    options: dict
    source: dict
    probabilities: str
    class_ids: list[int]
    groups: list[GroupResult]
    examples: list[Example] = field(default_factory=list)
    roi: torch.Tensor | None = None
    num_images: int = 0
    extra: dict = field(default_factory=dict)

    def __post_init__(self) -> None:  # the metrics' sums may be on a GPU (examples, roi: CPU)
        for result in self.groups:
            result.pixels, result.segments = _cpu(result.pixels), _cpu(result.segments)
            result.per_image, result.instances = _cpu(result.per_image), _cpu(result.instances)
        self.extra = _cpu(self.extra)

    def group(self, kind: str) -> GroupResult | None:
        """The result of the group of ``kind`` ("rules", "grid", "alpha"), if evaluated."""
        return next((g for g in self.groups if g.group.kind == kind), None)


def _cpu(value):
    """``value`` with every tensor in it (in dicts and lists) on the CPU."""
    if isinstance(value, torch.Tensor):
        return value.cpu()
    if isinstance(value, dict):
        return {k: _cpu(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_cpu(v) for v in value]
    return value
