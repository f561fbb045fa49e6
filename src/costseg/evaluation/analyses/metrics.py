"""The metrics of every rule group (docs/definitions.md §4, §9, §14): pixel counts per class and
RoI, segment errors, missed instances; the named rules' headline and each family's outputs
(:class:`~costseg.report.headline.GroupOutputs`). Validation during training measures the same
:class:`~costseg.metrics.scoring.GroupMetrics`."""

from __future__ import annotations

from costseg.classes import CLASS_NAMES, NUM_ROIS
from costseg.evaluation.analyses import Analysis, Seen
from costseg.metrics.scoring import GroupMetrics
from costseg.report.headline import GroupOutputs
from costseg.report.results import GroupResult


class RuleGroupMetrics(Analysis):
    def start(self) -> None:
        plan = self.context.plan
        classes, self.instances = plan.instance_classes
        self.metrics = [
            GroupMetrics(
                g,
                len(CLASS_NAMES),
                NUM_ROIS,
                None if g.temperature else plan.class_ids,
                plan.canvas,
                instance_classes=classes,
            ).to(plan.device)
            for g in self.context.groups
        ]

    def process(self, seen: Seen) -> None:
        batch = seen.batch
        for preds, metrics in zip(seen.preds, self.metrics, strict=True):
            metrics.update(preds, batch.labels, seen.roi, batch.instances)

    def result(self) -> GroupOutputs:
        groups = self.context.groups
        results = [GroupResult(g, **m.compute()) for g, m in zip(groups, self.metrics, strict=True)]
        return GroupOutputs(results, self.instances)


ANALYSIS = RuleGroupMetrics
