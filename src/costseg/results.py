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


@dataclass
class GroupResult:
    """One rule group's metrics: ``RoIPrecisionRecall.compute()`` and ``SegmentErrors.compute()``
    (see :mod:`costseg.metrics`), plus per-image counts when a guarantee needs them."""

    group: RuleGroup
    pixels: dict[str, torch.Tensor]
    segments: dict[str, torch.Tensor]
    per_image: dict[str, torch.Tensor] = field(default_factory=dict)

    def rows(self, class_ids: Sequence[int], rois: Sequence[int] = ROIS) -> list[dict]:
        """One row per rule × class × RoI: precision, recall, segment counts and rates, mIoU.

        The rule is identified by the group's columns (``matrix``; ``alpha, beta, gamma``; or
        ``prior_alpha``). NaN marks an undefined ratio.
        """
        pixels, seg = self.pixels, self.segments
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
                            "fp_segments": int(seg["fp"][k, c, r]),
                            "fn_segments": int(seg["fn"][k, c, r]),
                            "n_pred_segments": int(seg["n_pred"][k, c, r]),
                            "n_gt_segments": int(seg["n_gt"][k, c, r]),
                            "fp_rate": seg["fp_rate"][k, c, r].item(),
                            "fn_rate": seg["fn_rate"][k, c, r].item(),
                            "miou": pixels["miou"][k].item(),
                        }
                    )
        return rows


@dataclass
class Example:
    """One image of the mask figures: (3, H, W) uint8, (H, W) labels, (K, H, W) named-rule maps."""

    image: torch.Tensor
    label: torch.Tensor
    preds: torch.Tensor


@dataclass
class EvalResults:
    """Everything the report needs about one evaluation.

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

    def group(self, kind: str) -> GroupResult | None:
        """The result of the group of ``kind`` ("rules", "grid", "alpha"), if evaluated."""
        return next((g for g in self.groups if g.group.kind == kind), None)
