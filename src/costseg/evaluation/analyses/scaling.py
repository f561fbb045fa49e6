"""``--calibrate``: fit a temperature or a vector scaling of the logits on the held-out images
(docs/definitions.md §6); every later analysis sees the scaled probabilities. With
``--temperature_sweep``, the named rules at the fitted T join the sweep's groups."""

from __future__ import annotations

from costseg.calibration.sample import PixelSampler
from costseg.evaluation.analyses import Analysis
from costseg.rules import named_group, temperature_group

PIXELS_PER_IMAGE = 4096
"""Pixels of each held-out image the scaling is fitted on (docs/definitions.md §6)."""


class Scaling(Analysis):
    def fit(self) -> None:
        plan = self.context.plan
        sampler = PixelSampler(PIXELS_PER_IMAGE)
        for batch in self.context.held_out.batches("fit scaling"):
            sampler.update(plan.source.logits_of(batch.scores).cpu(), batch.labels.cpu())
        if sampler.num_images == 0:
            raise ValueError("no calibration image to fit the scaling on")
        scaling = sampler.fit(self.opts.calibrate)
        print(f"calibration: {scaling.describe()}")
        self.context.scaling = scaling
        if self.opts.temperature_sweep and scaling.kind == "temperature":
            named = named_group(self.context.groups)
            self.context.groups.append(temperature_group(named.rules, scaling.temperature))


ANALYSIS = Scaling
