"""``--guarantee``: Learn-then-Test on the held-out images (docs/definitions.md §7) chooses the
candidate of the sweep whose risk of missing ``--target`` is at most α with probability
1 − δ, the best of them by ``--maximize``."""

from __future__ import annotations

import torch

from costseg.calibration.guarantee import learn_then_test_paths
from costseg.classes import CLASS_NAMES, NUM_ROIS
from costseg.evaluation.analyses import Analysis, Context
from costseg.evaluation.settings import SweepChoice
from costseg.metrics.names import INSTANCE_RATES, SEGMENT_RATES
from costseg.metrics.per_image import per_image_counts, per_image_loss
from costseg.metrics.scoring import GroupMetrics
from costseg.metrics.selection import metric_values, parse_metric, parse_target, risk_level
from costseg.report.guarantee import Certificate


class Guarantee(Analysis):
    settings: SweepChoice

    def fit(self) -> None:
        self.certificate = certify(self.context, self.settings)

    def result(self) -> Certificate:
        return self.certificate


def certify(context: Context, choice: SweepChoice) -> Certificate:
    """Learn-then-Test on the calibration images: the certified rules of the candidates whose
    risk ``E[L_i]`` of the target's per-image loss is ≤ α (``--target``: α = 1 − 0.95 for
    ``recall>=0.95``; the segment rates' ``<=`` value as it is), and the best of them by
    ``--maximize`` (``choice``); among certified rules of the same best value, the one of largest
    ``group.prefer`` (the defer sweep: the larger defer cost)."""
    plan = context.plan
    index, group = next((i, g) for i, g in enumerate(context.groups) if g.candidates)
    t, goal = parse_target(choice.target), parse_metric(choice.maximize)
    named = {t.cls} | ({goal.cls} if goal.metric in SEGMENT_RATES else set())
    segments = sorted({*plan.class_ids, *named} - {None})  # None: all classes (coverage)
    wanted = {m.cls for m in (t, goal) if m.metric in INSTANCE_RATES}
    metrics = GroupMetrics(
        group, len(CLASS_NAMES), NUM_ROIS, segments, instance_classes=sorted(wanted)
    )
    counts, n = [], 0
    with torch.inference_mode():
        for seen in context.held_out_seen("certify"):
            labels, ids, preds = seen.batch.labels, seen.batch.instances, seen.preds[index]
            metrics.to(labels.device)  # a no-op after the first batch
            metrics.update(preds, labels, seen.roi, ids)
            counts.append(
                per_image_counts(
                    preds, labels, seen.roi, t.cls, t.roi, t.metric, instances=ids
                ).cpu()
            )
            n += len(labels)
    losses = per_image_loss(torch.cat(counts), t.metric).numpy()
    alpha = risk_level(t)
    ltt = learn_then_test_paths(losses, alpha, choice.delta, choice.method, group.paths)
    pooled = metrics.compute()
    objective = metric_values(
        pooled["pixels"], pooled["segments"], goal, segments, pooled["instances"]
    )
    # None unless a certified λ has a finite value
    chosen = ltt.best(objective.cpu().numpy(), prefer=group.prefer)
    return Certificate(group, ltt, chosen, objective, choice.target, choice.maximize, n)


ANALYSIS = Guarantee
