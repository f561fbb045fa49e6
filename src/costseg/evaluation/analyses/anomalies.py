"""``--anomalies``: anomaly scores of every reported image of the procedural scenes with unknown
objects, their pixel and component metrics, and what each named rule decides on the unknown
objects' pixels (docs/definitions.md §17)."""

from __future__ import annotations

from costseg.classes import CLASS_NAMES
from costseg.evaluation.analyses import Analysis, Seen
from costseg.evaluation.anomalies import AnomalyPass
from costseg.evaluation.processes import in_image_order
from costseg.evaluation.settings import ExampleSettings
from costseg.report.anomalies import AnomalyOutputs
from costseg.rules import named_group


class Anomalies(Analysis):
    settings: ExampleSettings
    every_entropy = True  # the mutual information score, on every image

    def start(self) -> None:
        rules = named_group(self.context.groups).rules
        self.found = AnomalyPass(rules, len(CLASS_NAMES), self.settings.num_examples)

    def process(self, seen: Seen) -> None:
        batch = seen.batch
        self.found.update(
            batch.images, seen.probs, batch.anomalies, seen.named, seen.priors,
            batch.expected_entropy, seen.positions, seen.roi,
        )  # fmt: skip

    def gather(self) -> None:
        self.examples = in_image_order(self.found.examples)

    def result(self) -> AnomalyOutputs:
        found = self.found.result()
        return AnomalyOutputs(found["scores"], found["decided"], self.examples)


ANALYSIS = Anomalies
