"""ECE, class-wise ECE, NLL and Brier score of the reported images' probabilities, before and
after a fitted scaling (docs/definitions.md §6)."""

from __future__ import annotations

from costseg.classes import CLASS_NAMES
from costseg.evaluation.analyses import Analysis, Seen
from costseg.metrics import CalibrationError
from costseg.report.calibration import CalibrationOutputs


class Calibration(Analysis):
    def start(self) -> None:
        device = self.context.plan.device
        self.scaled = self.context.scaling.kind != "none"
        self.ece = {"raw": CalibrationError(len(CLASS_NAMES)).to(device)}
        if self.scaled:
            self.ece["scaled"] = CalibrationError(len(CLASS_NAMES)).to(device)

    def process(self, seen: Seen) -> None:
        labels = seen.batch.labels
        if self.scaled:
            self.ece["scaled"].update(seen.probs, labels)
        self.ece["raw"].update(seen.unscaled, labels)

    def result(self) -> CalibrationOutputs:
        scaling = self.context.scaling
        record = scaling.to_dict() if self.scaled else None
        return CalibrationOutputs({k: m.compute() for k, m in self.ece.items()}, record)


ANALYSIS = Calibration
