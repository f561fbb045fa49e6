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
) -> SegmentTable:
    """The segments of ``labels`` (H, W), ``rule``'s decisions on the one image in ``probs``
    (1, N, H, W), with the features of the rule's heat maps (and the targets of ``gt``)."""
    maps = heat_maps(probs, rule, priors, expected_entropy)
    heat = {name: m[0].cpu().numpy() for name, m in maps.items()}
    return segment_features(labels, probs[0].float().cpu().numpy(), heat, gt)


class SegmentCollector:
    """Collects, image after image, the segment table of each of ``rules``.

    Args:
        rules: the rules whose label maps are described (their names key the tables).
        keep_maps: images whose segment ids (and per-segment values) are kept for figures.
    """

    def __init__(self, rules: Sequence[Rule], keep_maps: int = 0) -> None:
        self.rules = list(rules)
        self.keep_maps = keep_maps
        self.parts: dict[str, list[dict[str, np.ndarray]]] = {r.name: [] for r in self.rules}
        self.maps: list[dict[str, np.ndarray]] = []  # per kept image: rule → (H, W) ids
        self.images: list[str] = []

    def add(
        self,
        probs: torch.Tensor,
        preds: torch.Tensor,
        labels: torch.Tensor | None,
        priors: torch.Tensor | None,
        expected_entropy: torch.Tensor | None,
        stems: Sequence[str],
    ) -> None:
        """One batch: (B, N, H, W) probabilities, (B, K, H, W) label maps of the K rules,
        (B, H, W) ground truth or None, the priors and the runs' expected entropy (or None)."""
        for b, stem in enumerate(stems):
            gt = None if labels is None else labels[b].cpu().numpy()
            runs = None if expected_entropy is None else expected_entropy[b : b + 1]
            kept = {}
            for k, rule in enumerate(self.rules):
                labels_k = preds[b, k].cpu().numpy()
                table = rule_segments(probs[b : b + 1], labels_k, rule, priors, runs, gt)
                columns = dict(table.columns)
                columns["image"] = np.full(table.count, len(self.images))
                columns["segment"] = np.arange(1, table.count + 1)
                self.parts[rule.name].append(columns)
                kept[rule.name] = table.ids
            if len(self.maps) < self.keep_maps:
                self.maps.append(kept)
            self.images.append(stem)

    def features(self, rule: str) -> list[str]:
        """The feature columns of ``rule``'s tables (targets, image and segment ids left out)."""
        first = next((c for c in self.parts[rule]), None)
        heat = [h for h in (*HEAT_MAPS, "MI") if first is not None and h in first]
        num_classes = 0 if first is None else sum(k.startswith("cprob") for k in first)
        return feature_names(heat, num_classes)

    def table(self, rule: str) -> dict[str, np.ndarray]:
        """Every segment of ``rule`` over the images so far: column → (n,) values."""
        parts = self.parts[rule]
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
