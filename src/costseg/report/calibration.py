"""Outputs about the probabilities: ``calibration.json`` and ``calibration.csv`` (scaling; ECE,
class-wise ECE, NLL and Brier score before / after) and ``figures/reliability.png``.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import torch

from costseg.classes import CLASS_NAMES
from costseg.report.curves import reliability_figures
from costseg.report.drawing import job
from costseg.report.files import write_csv, write_json
from costseg.report.results import EvalResults
from costseg.report.sections import Result, Section
from costseg.report.tables import markdown_table

SCORES = ("ece", "classwise_ece", "nll", "brier")  # docs/definitions.md §6, §13


def calibration_rows(ece: Mapping[str, Mapping[str, torch.Tensor]]) -> list[dict]:
    """One row per set of probabilities (raw, scaled): its :data:`SCORES` and the ECE of the
    pixels predicted as each class (``ece_<class>``; NaN for a class never predicted)."""
    return [
        {"probabilities": name}
        | {score: float(out[score]) for score in SCORES}
        | {f"ece_{c}": float(v) for c, v in zip(CLASS_NAMES, out["per_class"], strict=False)}
        for name, out in ece.items()
    ]


def calibration_record(rows: list[dict]) -> dict:
    """``{score: {probabilities: value}}`` of :func:`calibration_rows`, and "ece_per_class"
    ``{probabilities: {class: value}}``, for results.json and calibration.json."""
    record = {score: {r["probabilities"]: r[score] for r in rows} for score in SCORES}
    record["ece_per_class"] = {
        r["probabilities"]: {c: r[f"ece_{c}"] for c in CLASS_NAMES if f"ece_{c}" in r} for r in rows
    }
    return record


def calibration_line(rows: list[dict]) -> str:
    """``calibration (15 bins): raw ECE 0.1234, class-wise ECE …, NLL …, Brier …; scaled …``."""
    return "calibration (15 bins): " + "; ".join(
        f"{r['probabilities']} ECE {r['ece']:.4f}, class-wise ECE {r['classwise_ece']:.4f}, "
        f"NLL {r['nll']:.4f}, Brier {r['brier']:.4f}"
        for r in rows
    )


@dataclass
class CalibrationOutputs(Result):
    """The calibration scores of the reported images' probabilities (docs/definitions.md §6).

    Attributes:
        ece: ``raw`` (and ``scaled`` after a scaling) → ``CalibrationError.compute()``.
        scaling: the fitted scaling's record, or None.
    """

    ece: dict[str, dict[str, torch.Tensor]]
    scaling: dict | None

    def rows(self) -> list[dict]:
        """:func:`calibration_rows` of these scores."""
        return calibration_rows(self.ece)

    def write(self, results: EvalResults) -> Section:
        """``calibration.json`` / ``.csv``, ``figures/reliability.png``, and the scores in
        results.json and TensorBoard."""
        rows, out = self.rows(), results.output_dir
        record = {"probabilities": results.probabilities, "scaling": self.scaling}
        write_json(out / "calibration.json", record | calibration_record(rows))
        section = Section(json={"scaling": self.scaling} | calibration_record(rows))
        if rows:
            write_csv(out / "calibration.csv", rows)
            section.console.append(calibration_line(rows))
            section.tables["evaluation/calibration"] = markdown_table(rows)
        section.jobs.append(("calibration", job(reliability_figures, self.ece, results.subject)))
        return section
