"""``evaluate.py --anomalies``: the anomaly scores of every reported image and their metrics
(docs/definitions.md §17).

Scores per pixel, each in [0, 1], higher = more likely unknown: ``max_softmax`` 1 − max p;
``entropy`` the normalised entropy E of §15; ``mutual_information`` MI / log N, where the source
has several runs (Monte-Carlo dropout, an ensemble); ``cost_margin/<rule>`` 1 / (1 + R) with R
the rule's cost margin (§15) in units of its smallest off-diagonal cost (the altruistic matrix's
costs span 0.1 to 1000, and its margins lie between its small costs), for every named rule.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
from torch import Tensor

from costseg.costs import cost_or_symmetric, off_diagonal
from costseg.meta.heat_maps import cost_margin, heat_maps
from costseg.metrics.anomaly import AnomalyMetrics
from costseg.rules import Rule


def anomaly_scores(
    probs: Tensor,
    rules: Sequence[Rule],
    priors: Tensor | None,
    expected_entropy: Tensor | None,
    roi: Tensor | None = None,
) -> dict[str, Tensor]:
    """name → (B, H, W) score, in the order of the module's docstring (``roi``: the RoI map of a
    regional rule)."""
    maps = heat_maps(probs, None, None, expected_entropy)
    scores = {"max_softmax": 1 - probs.float().amax(1), "entropy": maps["E"]}
    if "MI" in maps:
        scores["mutual_information"] = maps["MI"] / math.log(probs.shape[1])
    for rule in rules:
        margin = cost_margin(probs, rule, priors, roi) * _max_over_min_cost(rule, probs.shape[1])
        scores[f"cost_margin/{rule.name}"] = 1 / (1 + margin)
    return scores


def _max_over_min_cost(rule: Rule, n: int) -> float:
    """R is in units of the largest off-diagonal cost; this turns it into units of the
    smallest (of a regional rule: over all its matrices)."""
    off = off_diagonal(cost_or_symmetric(rule.cost, n))
    return float(off.max() / off.min())


class AnomalyPass:
    """The anomaly metrics of one evaluation, fed batch by batch (the scores' names are known at
    the first batch: mutual information only where the source has several runs)."""

    def __init__(self, rules: Sequence[Rule], num_classes: int, num_examples: int) -> None:
        self.rules, self.num_classes, self.num_examples = list(rules), num_classes, num_examples
        self.metric: AnomalyMetrics | None = None
        # for the figures: (position among the reported images, (image, mask, score maps))
        self.examples: list[tuple[int, tuple[Tensor, Tensor, dict[str, Tensor]]]] = []

    def update(
        self,
        images: Tensor,
        probs: Tensor,
        masks: Tensor,
        preds: Tensor,
        priors: Tensor | None,
        expected_entropy: Tensor | None,
        positions: Sequence[int],
        roi: Tensor | None = None,
    ) -> None:
        """``images`` (B, 3, H, W) uint8; ``preds``: (B, R, H, W) the named rules' label maps;
        ``positions``: the images' positions among the reported ones (the first
        ``num_examples`` are kept for the figures); ``roi``: the RoI map of regional rules."""
        scores = anomaly_scores(probs, self.rules, priors, expected_entropy, roi)
        for i, position in enumerate(positions):
            if position < self.num_examples:
                maps = {k: v[i].half().cpu() for k, v in scores.items()}
                example = (images[i].permute(1, 2, 0).cpu(), masks[i].cpu(), maps)
                self.examples.append((position, example))
        if self.metric is None:
            self.metric = AnomalyMetrics(list(scores), len(self.rules), self.num_classes)
            self.metric.to(probs.device)
        self.metric.update(torch.stack(list(scores.values())), masks, preds.transpose(0, 1))

    def result(self) -> dict:
        """``scores`` (name → metrics) and ``decided`` (rule → (N + 1,) counts)."""
        assert self.metric is not None, "no batch was seen"
        out = self.metric.compute()
        decided = {rule.name: out["decided"][r].tolist() for r, rule in enumerate(self.rules)}
        return {"scores": out["scores"], "decided": decided}
