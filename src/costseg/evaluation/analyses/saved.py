"""Per-image outputs: each image's probabilities (``--save-probs``: float16 ``probs/*.npz`` with
their uncertainty maps and the folder's data record, docs/definitions.md §8) and the named
rules' label-id PNGs (``--save-predictions``)."""

from __future__ import annotations

from costseg.evaluation.analyses import Analysis, Seen
from costseg.evaluation.processes import rank
from costseg.evaluation.settings import SavedSettings
from costseg.networks.probs_files import save_data_record
from costseg.report.outputs import BatchWriter
from costseg.rules import named_group


class SavedOutputs(Analysis):
    settings: SavedSettings

    @property
    def every_entropy(self) -> bool:  # the saved mutual information, on every image
        return self.settings.probs

    def start(self) -> None:
        plan = self.context.plan
        names = named_group(self.context.groups).names
        self.writer = BatchWriter(plan.output_dir, names, self.settings.predictions)
        if self.settings.probs and plan.data is not None and rank() == 0:
            save_data_record(plan.output_dir / "probs", plan.data, plan.priors.priors)

    def process(self, seen: Seen) -> None:
        stems = seen.batch.stems
        if self.settings.probs:  # as evaluated: rounded, so --probs reproduces the evaluation
            self.writer.save_probs(stems, seen.probs, seen.uncertainty)
        self.writer.save_predictions(stems, seen.named)


ANALYSIS = SavedOutputs
