"""The held-out calibration images: fit a scaling (docs/definitions.md §6) and certify a value
system (§7).

Both run before the reported images are seen, on images disjoint from them, each in one pass
of the network over the calibration images.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from costseg.calibration.guarantee import LTTResult, learn_then_test_paths
from costseg.calibration.sample import PixelSampler
from costseg.calibration.scaling import Scaling
from costseg.classes import CLASS_NAMES, NUM_ROIS
from costseg.metrics.names import INSTANCE_RATES, SEGMENT_RATES
from costseg.metrics.per_image import per_image_counts, per_image_loss
from costseg.metrics.scoring import GroupMetrics, score_batch
from costseg.metrics.selection import metric_values, parse_metric, parse_target, risk_level
from costseg.networks.sources import Source
from costseg.rules import RuleGroup


def fit_scaling(batches, kind: str, source: Source, pixels_per_image: int = 4096) -> Scaling:
    """Fit ``kind`` ("temperature" or "vector") on a sample of pixels of every batch of
    ``source``'s scores."""
    sampler = PixelSampler(pixels_per_image)
    for batch in batches:
        sampler.update(source.logits_of(batch.scores).cpu(), batch.labels.cpu())
    if sampler.num_images == 0:
        raise ValueError("no calibration image to fit the scaling on")
    return sampler.fit(kind)


@dataclass
class Certificate:
    """The value system chosen with a guarantee (Learn-then-Test over a rule group).

    Attributes:
        group: the candidates (grid points, α values, or rules at defer costs).
        ltt: the test's outcome (p-values, risks, images used and left out).
        chosen: index of the certified candidate with the best ``maximize`` on the
            calibration images, or None when nothing is certified.
        objective: (K,) pooled value of ``maximize`` on the calibration images.
        target, maximize: the texts asked; ``num_images``: calibration images.
    """

    group: RuleGroup
    ltt: LTTResult
    chosen: int | None
    objective: torch.Tensor
    target: str
    maximize: str
    num_images: int


def certify(
    batches,
    group: RuleGroup,
    probabilities,
    priors_at,
    target: str,
    maximize: str,
    delta: float,
    method: str,
    class_ids: list[int],
) -> Certificate:
    """Learn-then-Test on the calibration images: the certified rules of ``group`` whose risk
    ``E[L_i]`` of the target's per-image loss is ≤ α, and the best of them by ``maximize``.

    Args:
        batches: the calibration batches (:class:`~costseg.networks.sources.Batch`).
        group: the candidate rules.
        probabilities: ``batch → (B, N, H, W)`` probabilities the rules see.
        priors_at: ``(h, w) → (priors, roi)``.
        target: e.g. ``person:roi1:recall>=0.95`` (α = 1 − 0.95 for recall and precision,
            0.05 for the segment rates with ``<=``).
        maximize: e.g. ``person:roi1:precision``.
        delta: δ; method: ``bonferroni`` or ``fixed_sequence`` (along the group's order, or
            along each of its ``paths`` at δ / len(paths)).
        class_ids: classes of the segment metrics.

    Among certified rules of the same best ``maximize``, the one of largest ``group.prefer``
    (the defer sweep: the larger defer cost).
    """
    t, goal = parse_target(target), parse_metric(maximize)
    alpha = risk_level(t)
    named = {t.cls} | ({goal.cls} if goal.metric in SEGMENT_RATES else set())
    segments = sorted({*class_ids, *named} - {None})  # None: all classes (coverage)
    wanted = {m.cls for m in (t, goal) if m.metric in INSTANCE_RATES}
    metrics = GroupMetrics(
        group, len(CLASS_NAMES), NUM_ROIS, segments, instance_classes=sorted(wanted)
    )
    counts, n = [], 0
    for batch in batches:
        priors, roi = priors_at(tuple(batch.labels.shape[-2:]))
        metrics.to(batch.labels.device)  # a no-op after the first batch
        probs, ids = probabilities(batch), batch.instances
        preds = score_batch(group, metrics, probs, batch.labels, priors, roi, ids)
        counts.append(
            per_image_counts(preds, batch.labels, roi, t.cls, t.roi, t.metric, instances=ids).cpu()
        )
        n += len(batch.labels)
    losses = per_image_loss(torch.cat(counts), t.metric).numpy()
    ltt = learn_then_test_paths(losses, alpha, delta, method, group.paths)
    pooled = metrics.compute()
    objective = metric_values(
        pooled["pixels"], pooled["segments"], goal, segments, pooled["instances"]
    )
    # None unless a certified λ has a finite value
    chosen = ltt.best(objective.cpu().numpy(), prefer=group.prefer)
    return Certificate(group, ltt, chosen, objective, target, maximize, n)
