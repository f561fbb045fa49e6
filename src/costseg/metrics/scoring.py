"""The step shared by validation and evaluation: probabilities → rule groups → metrics.

>>> import torch
>>> from costseg.rules import parse_rules, rules_group
>>> group = rules_group(parse_rules(["robotistic", "egoistic"]))
>>> metrics = GroupMetrics(group, num_classes=19, num_rois=0)
>>> probs = torch.rand(1, 19, 4, 4).softmax(1)
>>> preds = score_batch(group, metrics, probs, probs.argmax(1))
>>> metrics.compute()["pixels"]["miou"][0].item()       # robotistic = argmax
1.0
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from torch import Tensor
from torchmetrics.wrappers.abstract import WrapperMetric

from costseg.classes import NUM_ROIS
from costseg.metrics.instances import InstanceMisses
from costseg.metrics.roi import RoIPrecisionRecall
from costseg.metrics.segments import SegmentErrors
from costseg.rules import RuleGroup


class GroupMetrics(WrapperMetric):
    """The metrics of one rule group: pixel counts per RoI and, optionally, segment errors and
    missed instances.

    A torchmetrics wrapper: it holds no state of its own; its metrics sum and synchronise
    theirs, so it merges across batches and processes like them and fits in a
    :class:`torchmetrics.MetricCollection`.

    Args:
        group: the rule group (its K rules).
        num_classes: N.
        num_rois: R (street, sidewalk, building, sky: :data:`costseg.classes.ROI_NAMES`).
        segment_classes: classes of the segment metrics; None = no segment metrics.
        heatmap_size: (h, w) canvas of the FP/FN location maps (see :class:`SegmentErrors`);
            ignored for groups without heatmaps.
        instance_classes: classes of the instance metrics (:class:`InstanceMisses`); None or
            empty = none (then ``update`` ignores instance ids).
        kwargs: torchmetrics' options of every ``Metric``, passed to each metric.
    """

    def __init__(
        self,
        group: RuleGroup,
        num_classes: int,
        num_rois: int = NUM_ROIS,
        segment_classes: Sequence[int] | None = None,
        heatmap_size: tuple[int, int] | None = None,
        instance_classes: Sequence[int] | None = None,
        **kwargs: Any,
    ) -> None:
        super().__init__()
        k = len(group.names)
        self.pixels = RoIPrecisionRecall(num_classes, k, num_rois, **kwargs)
        self.segments = None
        if segment_classes:
            size = heatmap_size if group.heatmaps else (0, 0)
            self.segments = SegmentErrors(segment_classes, k, num_rois, heatmap_size=size, **kwargs)
        self.instances = None
        if instance_classes:
            size = heatmap_size if group.heatmaps and heatmap_size else (0, 0)
            self.instances = InstanceMisses(
                instance_classes, k, num_rois, heatmap_size=size, **kwargs
            )

    def _children(self) -> dict[str, Any]:
        named = {"pixels": self.pixels, "segments": self.segments, "instances": self.instances}
        return {name: metric for name, metric in named.items() if metric is not None}

    def update(
        self,
        preds: Tensor,
        target: Tensor,
        roi: Tensor | None = None,
        instances: Tensor | None = None,
    ) -> None:
        """Add (B, K, H, W) decisions of the group for (B, H, W) labels (and instance ids)."""
        for name, metric in self._children().items():
            if name != "instances":
                metric.update(preds, target, roi)
            elif instances is not None:
                metric.update(preds, target, instances, roi)

    def compute(self) -> dict[str, dict[str, Tensor]]:
        """``{"pixels": RoIPrecisionRecall.compute(), "segments": SegmentErrors.compute(),
        "instances": InstanceMisses.compute()}`` (``{}`` for metrics not measured)."""
        out = {"pixels": {}, "segments": {}, "instances": {}}
        out |= {name: metric.compute() for name, metric in self._children().items()}
        return out

    def reset(self) -> None:
        """Back to the metrics' default states."""
        for metric in self._children().values():
            metric.reset()
        super().reset()


def score_batch(
    group: RuleGroup,
    metrics: GroupMetrics,
    probs: Tensor,
    labels: Tensor,
    priors: Tensor | None = None,
    roi: Tensor | None = None,
    instances: Tensor | None = None,
) -> list[Tensor]:
    """Decide the group on (B, N, H, W) probabilities, update its metrics, return the maps.

    Args:
        group: the rule group.
        metrics: its :class:`GroupMetrics`.
        probs: (B, N, H, W) probabilities.
        labels: (B, H, W) train ids (255 = ignore).
        priors: None, (N,) or (N, H, W) pixel-wise priors.
        roi: None or (H, W) RoI ids (a regional rule decides with them).
        instances: None or (B, H, W) instance ids (for groups with instance metrics).

    Returns:
        the (B, K, H, W) label maps.
    """
    preds = group.decide(probs, priors, roi)
    metrics.update(preds, labels, roi, instances)
    return preds
