"""``--calibrate``: fit a temperature or a vector scaling of the logits on the held-out images
(docs/definitions.md §6); every later analysis sees the scaled probabilities. With
``--temperature_sweep``, the named rules at the fitted T join the sweep's groups."""

from __future__ import annotations

from costseg.calibration.sample import PixelSampler
from costseg.evaluation.analyses import Analysis, Provided
from costseg.evaluation.settings import ScalingSettings
from costseg.rules import named_group, temperature_group

PIXELS_PER_IMAGE = 4096
"""Pixels of each held-out image the scaling is fitted on (docs/definitions.md §6)."""


class Scaling(Analysis):
    settings: ScalingSettings

    def fit(self) -> Provided:
        source = self.context.plan.source
        sampler = PixelSampler(PIXELS_PER_IMAGE)
        for seen in self.context.held_out_seen("fit scaling"):
            sampler.update(source.logits_of(seen.batch.scores).cpu(), seen.batch.labels.cpu())
        if sampler.num_images == 0:
            raise ValueError("no calibration image to fit the scaling on")
        scaling = sampler.fit(self.settings.kind)
        print(f"calibration: {scaling.describe()}")
        if not (self.settings.temperature_sweep and scaling.kind == "temperature"):
            return Provided(scaling=scaling)
        named = named_group(self.context.groups)
        return Provided(scaling, groups=(temperature_group(named.rules, scaling.temperature),))


ANALYSIS = Scaling
