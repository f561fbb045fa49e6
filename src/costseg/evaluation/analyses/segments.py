"""Segments (docs/definitions.md §15): every segment of the named rules' label maps with its
features (``--save-segments``), meta models fitted on the held-out images' segments and scored
on the reported ones (``--meta``), and the fused rules' models (``--fuse``)."""

from __future__ import annotations

from dataclasses import replace

import torch

from costseg.evaluation.analyses import Analysis, Context, Provided, Seen
from costseg.evaluation.processes import in_image_order
from costseg.evaluation.settings import SegmentSettings
from costseg.meta.collect import SegmentCollector
from costseg.meta.fusion import FUSED_FAMILY
from costseg.meta.models import MetaModels, fit_models
from costseg.meta.models import scores as meta_scores
from costseg.progress import progress
from costseg.report.segments import SegmentOutputs
from costseg.rules import Rule, RuleGroup, apply_rules, named_group


class Segments(Analysis):
    settings: SegmentSettings

    @property
    def every_entropy(self) -> bool:  # the features' mutual information, on every image
        return self.settings.meta or self.settings.save

    def fit(self) -> Provided | None:
        self.models = None
        if self.context.meta_held_out is None:
            return None
        self.models, fused = _fit_meta(self.context, self.settings.meta)
        return Provided(replaced=(fused,) if fused is not None else ())

    def start(self) -> None:
        self.collector = None
        if self.every_entropy:
            rules = named_group(self.context.groups).rules
            self.collector = SegmentCollector(rules, self.settings.num_examples)

    def process(self, seen: Seen) -> None:
        if self.collector is not None:
            batch = seen.batch
            self.collector.add(
                seen.probs, seen.named, batch.labels, seen.priors, batch.expected_entropy,
                batch.stems, seen.positions, seen.roi,
            )  # fmt: skip

    def gather(self) -> None:
        if self.collector is not None:
            self.collector.records = list(enumerate(in_image_order(self.collector.records)))

    def result(self) -> SegmentOutputs | None:
        collector = self.collector
        if collector is None:
            return None
        models = self.models if self.settings.meta else None
        tables = {r.name: collector.table(r.name) for r in collector.rules}
        segments = SegmentOutputs(
            tables, collector.images, collector.maps, models, save=self.settings.save
        )
        if models is not None:
            segments.scores = {r: meta_scores(models[r], tables[r]) for r in tables if tables[r]}
            segments.fitted_on = {
                "images": len(self.context.meta_held_out),
                "segments": {r: m.num_segments for r, m in models.items()},
            }
        return segments


def _fusion(groups: list[RuleGroup]) -> int | None:
    """The index of the fused rules' group in ``groups``, or None."""
    return next((i for i, g in enumerate(groups) if g.family == FUSED_FAMILY), None)


def _meta_rules(groups: list[RuleGroup], meta: bool) -> list[Rule]:
    """The rules whose segments the meta models judge: the named ones (``meta``) and the
    fused ones (``--fuse``)."""
    rules = list(named_group(groups).rules) if meta else []
    fusion = _fusion(groups)
    if fusion is not None:
        fused = groups[fusion].decide.fused
        rules += [r for r in fused if r.name not in {q.name for q in rules}]
    return rules


def _decided(seen: Seen, named: RuleGroup, rule: Rule) -> torch.Tensor:
    """(B, 1, H, W) ``rule``'s label maps: the named group's, or a fused rule's own."""
    if rule.name in named.names:
        return seen.named[:, [named.names.index(rule.name)]]
    return apply_rules(seen.probs, [rule], seen.priors, seen.roi)


def _fit_meta(context: Context, meta: bool) -> tuple[dict[str, MetaModels], RuleGroup | None]:
    """Fit the meta models of every rule of :func:`_meta_rules` on the segments of the held-out
    images; the fused rules get theirs (without MI: a rule decides from the probabilities) in
    a fused group that holds them (None without ``--fuse``)."""
    plan, held = context.plan, context.meta_held_out
    rules = _meta_rules(context.groups, meta)
    named = named_group(context.groups)
    collector = SegmentCollector(rules)
    with torch.inference_mode():
        for seen in context.held_out_seen("meta features", held):
            batch = seen.batch
            preds = torch.cat([_decided(seen, named, r) for r in rules], 1)
            collector.add(
                seen.probs,
                preds,
                batch.labels,
                seen.priors,
                batch.expected_entropy,
                batch.stems,
                roi=seen.roi,
            )
    fitting = "meta models, rule by rule" if plan.progress else None
    models = {
        r.name: fit_models(collector.table(r.name), collector.features(r.name), len(held))
        for r in progress(rules, fitting)
    }
    fitted = {r: m.num_segments for r, m in models.items()}
    print(f"meta models fitted on {len(held)} held-out images: segments {fitted}")
    fusion = _fusion(context.groups)
    if fusion is None:
        return models, None
    group, own = context.groups[fusion], {}
    for r in group.decide.fused:
        features = [f for f in collector.features(r.name) if not f.startswith("MI")]
        same = features == models[r.name].features
        own[r.name] = (
            models[r.name] if same else fit_models(collector.table(r.name), features, len(held))
        )
    return models, replace(group, decide=group.decide.using(own))


ANALYSIS = Segments
