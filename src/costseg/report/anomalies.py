"""The anomaly section of an evaluation (``--anomalies``, docs/definitions.md §17): per score its
pixel and component metrics, and per rule what it decides on the unknown objects' pixels, in
results.json, table.md and TensorBoard."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from costseg.classes import CLASS_NAMES
from costseg.report.anomaly_figures import anomaly_map_figures
from costseg.report.drawing import Job, job
from costseg.report.results import EvalResults
from costseg.report.sections import Result, Section
from costseg.report.tables import markdown_table

SCORE_COLUMNS = ("auroc", "ap", "fpr95", "delta", "pixel_f1", "siou", "ppv", "mean_f1")
SHOWN_CLASSES = 4  # the classes a rule gives most anomaly pixels, in table.md


def decided_shares(counts: list[int]) -> dict[str, float]:
    """Class (and ``deferred``) → share of the anomaly pixels, largest first.

    >>> decided_shares([1, 3] + [0] * 17 + [4])
    {'deferred': 0.5, 'sidewalk': 0.375, 'road': 0.125}
    """
    total = sum(counts) or 1
    names = [*CLASS_NAMES, "deferred"]
    shares = {names[c]: n / total for c, n in enumerate(counts) if n}
    return dict(sorted(shares.items(), key=lambda item: -item[1]))


def anomaly_json(found: dict[str, Any] | None) -> dict[str, Any] | None:
    """What results.json holds (None without ``--anomalies``)."""
    if found is None:
        return None
    decided = {rule: decided_shares(counts) for rule, counts in found["decided"].items()}
    return {"scores": found["scores"], "decided": decided, "decided_pixels": found["decided"]}


def anomaly_jobs(found: dict[str, Any] | None, subject: str = "") -> list[tuple[str, Job]]:
    """The figure job of the example images' score maps (none without ``--anomalies``), titled
    with ``subject`` (the network and shift)."""
    if not found or not found.get("examples"):
        return []
    return [("evaluation", job(anomaly_map_figures, found["examples"], subject))]


def anomaly_table(found: dict[str, Any] | None) -> str:
    """The section of table.md ("" without ``--anomalies``)."""
    if found is None:
        return ""
    rows = [{"score": name, **values} for name, values in found["scores"].items()]
    percent = ["auroc", "ap", "fpr95", "pixel_f1", "siou", "ppv", "mean_f1"]
    scores = markdown_table(rows, ["score", *SCORE_COLUMNS], percent=percent)
    decided = []
    for rule, counts in found["decided"].items():
        top = list(decided_shares(counts).items())[:SHOWN_CLASSES]
        decided.append(
            {"rule": rule, **{f"{k + 1}.": f"{c} {100 * v:.1f} %" for k, (c, v) in enumerate(top)}}
        )
    return "\n\n".join(
        [
            "## Unknown objects (definitions §17)",
            "Pixel AUROC, AP and FPR at 95 % TPR; SegmentMeIfYouCan's sIoU, PPV and mean F1 of"
            " the prediction score > δ, δ the threshold of the best pixel F1 (AnomalyTrack's"
            " least component sizes, scaled to the image area):",
            scores,
            "What each rule labels the unknown objects' pixels (share of their pixels):",
            markdown_table(decided, percent=[]),
        ]
    )


@dataclass
class AnomalyOutputs(Result):
    """The anomaly metrics of ``--anomalies``: ``scores`` (name → metrics), ``decided``
    (rule → (N + 1,) pixel counts) and the examples' score maps."""

    scores: dict[str, dict[str, float]]
    decided: dict[str, list[int]]
    examples: list

    def write(self, results: EvalResults) -> Section:
        """results.json and table.md sections, scalars and the score maps' figures."""
        found = {"scores": self.scores, "decided": self.decided, "examples": self.examples}
        curves = [
            (f"evaluation/anomaly/{k}/{name}", None, [0], [values[k]])
            for name, values in self.scores.items()
            for k in SCORE_COLUMNS
        ]
        return Section(
            json={"anomalies": anomaly_json(found)},
            table="\n\n" + anomaly_table(found) + "\n",
            curves=curves,
            jobs=anomaly_jobs(found, results.subject),
        )
