"""The segments of every image and rule, with their features and targets, as one table per rule
(docs/definitions.md §15): what the meta models learn from, ``segments/<rule>.csv`` holds, and
the figures draw.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch

from costseg.meta.features import SegmentTable, feature_names, segment_features
from costseg.meta.heat_maps import heat_maps
from costseg.meta.models import MetaModels
from costseg.rules.base import Rule

HEAT_MAPS = ("E", "D", "R")  # and MI where the source has several runs


def rule_segments(
    probs: torch.Tensor,
    labels: np.ndarray,
    rule: Rule,
    priors: torch.Tensor | None,
    expected_entropy: torch.Tensor | None,
    gt: np.ndarray | None = None,
    roi: torch.Tensor | None = None,
) -> SegmentTable:
    """The segments of ``labels`` (H, W), ``rule``'s decisions on the one image in ``probs``
    (1, N, H, W), with the features of the rule's heat maps (and the targets of ``gt``; ``roi``:
    the RoI map a regional rule decides with)."""
    maps = heat_maps(probs, rule, priors, expected_entropy, roi)
    heat = {name: m[0].cpu().numpy() for name, m in maps.items()}
    return segment_features(labels, probs[0].float().cpu().numpy(), heat, gt)


@dataclass
class ImageSegments:
    """The segments of one image: its name, each rule's segment table (column → (n,) values)
    and, for the first images, each rule's (H, W) segment ids (for figures)."""

    stem: str
    columns: dict[str, dict[str, np.ndarray]]
    maps: dict[str, np.ndarray] | None


class SegmentCollector:
    """Collects, image after image, the segment table of each of ``rules``.

    Args:
        rules: the rules whose label maps are described (their names key the tables).
        keep_maps: the first images (by position) whose segment ids are kept for figures.

    Attributes:
        records: ``(position, ImageSegments)`` of every image added; the tables list the images
            in the order of their positions (under ``torchrun``, every process's records
            gathered: :func:`costseg.evaluation.processes.in_image_order`).
    """

    def __init__(self, rules: Sequence[Rule], keep_maps: int = 0) -> None:
        self.rules = list(rules)
        self.keep_maps = keep_maps
        self.records: list[tuple[int, ImageSegments]] = []

    def add(
        self,
        probs: torch.Tensor,
        preds: torch.Tensor,
        labels: torch.Tensor | None,
        priors: torch.Tensor | None,
        expected_entropy: torch.Tensor | None,
        stems: Sequence[str],
        positions: Sequence[int] | None = None,
        roi: torch.Tensor | None = None,
    ) -> None:
        """One batch: (B, N, H, W) probabilities, (B, K, H, W) label maps of the K rules,
        (B, H, W) ground truth or None, the priors and the runs' expected entropy (or None),
        the images' names and positions (default: after the images added so far), the (H, W)
        RoI map (for regional rules)."""
        if positions is None:
            positions = range(len(self.records), len(self.records) + len(stems))
        for b, (stem, position) in enumerate(zip(stems, positions, strict=True)):
            gt = None if labels is None else labels[b].cpu().numpy()
            runs = None if expected_entropy is None else expected_entropy[b : b + 1]
            columns, maps = {}, {}
            for k, rule in enumerate(self.rules):
                labels_k = preds[b, k].cpu().numpy()
                table = rule_segments(probs[b : b + 1], labels_k, rule, priors, runs, gt, roi)
                columns[rule.name] = dict(table.columns)
                maps[rule.name] = table.ids
            kept = maps if position < self.keep_maps else None
            self.records.append((position, ImageSegments(stem, columns, kept)))

    @property
    def ordered(self) -> list[ImageSegments]:
        """The images' segments in the order of their positions."""
        return [record for _, record in sorted(self.records, key=lambda r: r[0])]

    @property
    def images(self) -> list[str]:
        """The images' names, in order."""
        return [image.stem for image in self.ordered]

    @property
    def maps(self) -> list[dict[str, np.ndarray]]:
        """Per kept image (the first ones), rule → (H, W) segment ids."""
        return [image.maps for image in self.ordered if image.maps is not None]

    def features(self, rule: str) -> list[str]:
        """The feature columns of ``rule``'s tables (targets, image and segment ids left out)."""
        first = self.records[0][1].columns[rule] if self.records else None
        heat = [h for h in (*HEAT_MAPS, "MI") if first is not None and h in first]
        num_classes = 0 if first is None else sum(k.startswith("cprob") for k in first)
        return feature_names(heat, num_classes)

    def table(self, rule: str) -> dict[str, np.ndarray]:
        """Every segment of ``rule`` over the images so far, in order: column → (n,) values
        (``image`` indexes :attr:`images`, ``segment`` numbers each image's segments from 1)."""
        parts = []
        for i, image in enumerate(self.ordered):
            columns = dict(image.columns[rule])
            count = len(columns["S"])
            columns["image"] = np.full(count, i)
            columns["segment"] = np.arange(1, count + 1)
            parts.append(columns)
        if not parts:
            return {}
        return {key: np.concatenate([p[key] for p in parts]) for key in parts[0]}


@dataclass
class SegmentResults:
    """The segments of the reported images and, with meta models, how well those models judge
    them.

    Attributes:
        tables: rule → column → (n,) values of every segment (``image`` indexes ``images``).
        images: the reported images' names, in order.
        maps: per kept image (the first ones), rule → (H, W) segment ids.
        models: rule → the meta models fitted on held-out images (None: no ``--meta``).
        scores: rule → model → AUROC, accuracy, R², σ, segments (:func:`~.models.scores`).
        fitted_on: what the models were fitted on (images, segments per rule).
    """

    tables: dict[str, dict[str, np.ndarray]]
    images: list[str]
    maps: list[dict[str, np.ndarray]]
    models: dict[str, MetaModels] | None = None
    scores: dict[str, dict[str, dict[str, float]]] | None = None
    fitted_on: dict | None = None

    def predicted(self, rule: str, model: str) -> dict[str, np.ndarray]:
        """The models' predicted IoU and probability of being false of ``rule``'s segments."""
        if not self.models or model not in self.models[rule].fitted:
            return {}
        m, table = self.models[rule], self.tables[rule]
        return {"iou": m.predicted_iou(model, table), "false": m.false_probability(model, table)}
