"""The first ``--num_examples`` reported images with every shown rule's label map and their
uncertainty maps (docs/definitions.md §13): the mask figures, TensorBoard and the explorer
(with ``--explorer``, their float16 probabilities too)."""

from __future__ import annotations

import torch

from costseg.evaluation.analyses import Analysis, Seen
from costseg.evaluation.processes import in_image_order
from costseg.evaluation.settings import ExampleSettings
from costseg.report.examples import ExampleOutputs
from costseg.report.results import Example
from costseg.rules import masked_groups


class Examples(Analysis):
    settings: ExampleSettings

    def start(self) -> None:
        groups = self.context.groups
        self.shown = [groups.index(g) for g in masked_groups(groups)]
        self.kept: list[tuple[int, Example]] = []  # (position among the reported images, example)

    def process(self, seen: Seen) -> None:
        batch = seen.batch
        kept = [i for i, p in enumerate(seen.positions) if p < self.settings.num_examples]
        if kept:
            preds = torch.cat([seen.preds[g] for g in self.shown], 1)
            maps = seen.uncertainty
        for i in kept:
            probs = seen.probs[i].to("cpu", torch.float16) if self.settings.keep_probs else None
            image, label = batch.images[i].cpu(), batch.labels[i].cpu()
            uncertainty = {k: v[i].to("cpu", torch.float16) for k, v in maps.items()}
            example = Example(image, label, preds[i].cpu(), batch.stems[i], probs, uncertainty)
            self.kept.append((seen.positions[i], example))
        if self.context.early is not None:  # drawn once this process holds every example
            examples = [example for _, example in self.kept]
            self.context.early.after_batch(examples, self.context.groups)

    def gather(self) -> None:
        self.examples = in_image_order(self.kept)

    def result(self) -> ExampleOutputs:
        early = self.context.early
        return ExampleOutputs(self.examples, drawn=early is not None and early.examples_started)


ANALYSIS = Examples
