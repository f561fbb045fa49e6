"""The step shared by validation and evaluation: probabilities → rule groups → metrics.

>>> import torch
>>> from costseg.rules import parse_rules, rules_group
>>> groups = [rules_group(parse_rules(["robotistic", "egoistic"]))]
>>> metrics = GroupMetrics(groups[0], num_classes=19, num_rois=0)
>>> probs = torch.rand(1, 19, 4, 4).softmax(1)
>>> preds = score_batch(groups, [metrics], probs, probs.argmax(1))
>>> metrics.compute()["pixels"]["miou"][0].item()       # robotistic = argmax
1.0
"""

from __future__ import annotations

from collections.abc import Sequence

from torch import Tensor, nn

from costseg.metrics import RoIPrecisionRecall, SegmentErrors
from costseg.metrics.instances import InstanceMisses
from costseg.rules import RuleGroup


class GroupMetrics(nn.Module):
    """The metrics of one rule group: pixel counts per RoI and, optionally, segment errors and
    missed instances.

    Args:
        group: the rule group (its K rules).
        num_classes: N.
        num_rois: R (4: street, sidewalk, building, sky).
        segment_classes: classes of the segment metrics; None = no segment metrics.
        heatmap_size: (h, w) canvas of the FP/FN location maps (see :class:`SegmentErrors`);
            ignored for groups without heatmaps.
        instance_classes: classes of the instance metrics (:class:`InstanceMisses`); None or
            empty = none (then ``update`` ignores instance ids).
    """

    def __init__(
        self,
        group: RuleGroup,
        num_classes: int,
        num_rois: int = 4,
        segment_classes: Sequence[int] | None = None,
        heatmap_size: tuple[int, int] | None = None,
        instance_classes: Sequence[int] | None = None,
    ) -> None:
        super().__init__()
        k = len(group.names)
        self.pixels = RoIPrecisionRecall(num_classes, num_rules=k, num_rois=num_rois)
        self.segments = None
        if segment_classes:
            size = heatmap_size if group.heatmaps else (0, 0)
            self.segments = SegmentErrors(segment_classes, k, num_rois, heatmap_size=size)
        self.instances = None
        if instance_classes:
            size = heatmap_size if group.heatmaps and heatmap_size else (0, 0)
            self.instances = InstanceMisses(instance_classes, k, num_rois, heatmap_size=size)

    def update(
        self, preds: Tensor, labels: Tensor, roi: Tensor | None, instances: Tensor | None = None
    ) -> None:
        """Add (B, K, H, W) decisions of the group for (B, H, W) labels (and instance ids)."""
        self.pixels.update(preds, labels, roi)
        if self.segments is not None:
            self.segments.update(preds, labels, roi)
        if self.instances is not None and instances is not None:
            self.instances.update(preds, labels, instances, roi)

    def compute(self) -> dict[str, dict[str, Tensor]]:
        """``{"pixels": RoIPrecisionRecall.compute(), "segments": SegmentErrors.compute(),
        "instances": InstanceMisses.compute()}`` (empty dicts for metrics not measured)."""
        out = {"pixels": self.pixels.compute()}
        out["segments"] = {} if self.segments is None else self.segments.compute()
        out["instances"] = {}
        if self.instances is not None:
            out["instances"] = self.instances.shaped(self.instances.compute())
        return out

    def reset(self) -> None:
        self.pixels.reset()
        if self.segments is not None:
            self.segments.reset()
        if self.instances is not None:
            self.instances.reset()


def score_batch(
    groups: Sequence[RuleGroup],
    metrics: Sequence[GroupMetrics],
    probs: Tensor,
    labels: Tensor,
    priors: Tensor | None = None,
    roi: Tensor | None = None,
    instances: Tensor | None = None,
) -> list[Tensor]:
    """Decide every group on (B, N, H, W) probabilities, update its metrics, return the maps.

    Args:
        groups: the rule groups.
        metrics: one :class:`GroupMetrics` per group.
        probs: (B, N, H, W) probabilities.
        labels: (B, H, W) train ids (255 = ignore).
        priors: None, (N,) or (N, H, W) pixel-wise priors.
        roi: None or (H, W) RoI ids.
        instances: None or (B, H, W) instance ids (for groups with instance metrics).

    Returns:
        per group the (B, K, H, W) label maps.
    """
    preds = [g.decide(probs, priors) for g in groups]
    for m, p in zip(metrics, preds, strict=True):
        m.update(p, labels, roi, instances)
    return preds
