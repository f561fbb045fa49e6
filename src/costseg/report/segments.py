"""The outputs of segment meta classification and fusion (docs/definitions.md §15):
``segments/<rule>.csv``, the meta models (``meta/models.joblib``), their scores in results.json,
table.md and TensorBoard, and their figures (:mod:`costseg.report.segment_figures`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from costseg.classes import CLASS_NAMES
from costseg.meta.collect import SegmentResults
from costseg.meta.models import MODELS, SHOWN_MODEL, save_models
from costseg.report.drawing import Job, job
from costseg.report.files import write_csv
from costseg.report.results import EvalResults, GroupResult
from costseg.report.sections import Result, Section
from costseg.report.segment_figures import (
    importance_figures,
    iou_scatter_figures,
    segment_iou_figures,
    tradeoff_figures,
)
from costseg.report.sweep import sweep_outputs
from costseg.report.tables import console_table, markdown_table

SCORES = ("auroc", "accuracy", "r2", "sigma", "segments")
MODELS_FILE = "meta/models.joblib"


def meta_rows(segments: SegmentResults | None) -> list[dict]:
    """One row per rule × model: its scores on the reported images' segments."""
    if segments is None or not segments.scores:
        return []
    return [
        {"matrix": rule, "model": model, **{s: values[s] for s in SCORES}}
        for rule, by_model in segments.scores.items()
        for model, values in by_model.items()
    ]


def meta_json(segments: SegmentResults | None) -> dict | None:
    """The record of results.json: what the models were fitted on, and their scores."""
    if segments is None or not segments.scores:
        return None
    return {"fitted_on": segments.fitted_on, "scores": segments.scores, "models": MODELS_FILE}


def meta_table(segments: SegmentResults | None) -> str:
    """The section of table.md (empty without ``--meta``)."""
    rows = meta_rows(segments)
    if not rows:
        return ""
    fitted = segments.fitted_on or {}
    return (
        "## Meta classification of segments (docs/definitions.md §15)\n\n"
        f"Fitted on the segments of {fitted.get('images')} held-out images, scored on the "
        "reported ones: AUROC and accuracy of iou0 (false segment), R² and σ of the IoU.\n\n"
        + markdown_table(rows)
    )


def meta_console(segments: SegmentResults | None) -> str:
    """The terminal's summary of ``--meta`` (empty without it): per rule, each model's AUROC of
    iou0 (a false segment) and R² of the IoU on the reported images.

    >>> scores = {m: {"auroc": 0.8, "r2": 0.5} for m in MODELS}
    >>> print(meta_console(SegmentResults({}, [], [], scores={"ml": scores})))
    meta models, scored on the reported images' segments: AUROC of iou0, R² of the IoU
    rule  AUROC logistic  AUROC boosting  AUROC entropy  R² logistic  R² boosting  R² entropy
    ----  --------------  --------------  -------------  -----------  -----------  ----------
    ml               0.8             0.8            0.8          0.5          0.5         0.5
    """
    if segments is None or not segments.scores:
        return ""
    scores = {"auroc": "AUROC", "r2": "R²"}
    columns = [(s, m) for s in scores for m in MODELS]
    rows = [
        {"rule": rule} | {f"{s} {m}": by_model.get(m, {}).get(s) for s, m in columns}
        for rule, by_model in segments.scores.items()
    ]
    names = [f"{s} {m}" for s, m in columns]
    headers = ["rule", *(f"{scores[s]} {m.replace('gradient_', '')}" for s, m in columns)]
    table = console_table(rows, ["rule", *names], headers, percent=())
    what = "meta models, scored on the reported images' segments: AUROC of iou0, R² of the IoU"
    return f"{what}\n{table}"


@dataclass
class SegmentOutputs(SegmentResults, Result):
    """The segments of the reported images (``--save-segments``: ``save``) and the meta models'
    scores on them (``--meta``)."""

    save: bool = False  # segments/<rule>.csv

    def write(self, results: EvalResults) -> Section:
        """``segments/<rule>.csv``, ``meta/models.joblib``, the scores in results.json, table.md,
        the terminal and TensorBoard, and the figures."""
        out, section = results.output_dir, Section(json={"meta": meta_json(self)})
        if self.save:
            for rule, table in self.tables.items():
                write_csv(out / "segments" / f"{rule}.csv", _csv_rows(self, rule, table))
        if not self.models:
            return section
        save_models(out / MODELS_FILE, self.models)
        if meta := meta_console(self):
            section.console.append(meta)
        if meta := meta_table(self):
            section.table = "\n\n" + meta + "\n"
        for row in meta_rows(self):
            for score in SCORES[:-1]:
                tag = f"meta/{row['matrix']}/{row['model']}/{score}"
                section.curves.append((tag, None, [0], [row[score]]))
        section.jobs += _meta_jobs(self, results)
        return section


def fusion_outputs(results: EvalResults, mine: list[GroupResult]) -> Section:
    """The fused rules' rows and curves (:func:`~costseg.report.sweep.sweep_outputs`) and the
    trade-off of each fused rule over τ."""
    section = sweep_outputs(results, mine)
    section.jobs += _fusion_jobs(results, mine[0])
    return section


def _csv_rows(segments: SegmentResults, rule: str, table: dict[str, np.ndarray]) -> list[dict]:
    """One row per segment: its image's name, its id, its features and targets, and each
    model's predicted IoU and probability of being false."""
    columns = {k: v for k, v in table.items() if k not in ("image", "segment")}
    for model in MODELS:
        for key, values in segments.predicted(rule, model).items():
            columns[f"{model}_{key}"] = values
    integers = {"class", "S", "S_in", "S_bd", "iou0"}
    return [
        {"image": segments.images[image], "segment": int(table["segment"][i])}
        | {k: int(v[i]) if k in integers else float(v[i]) for k, v in columns.items()}
        for i, image in enumerate(table.get("image", []))
    ]


def _meta_jobs(segments: SegmentResults, results: EvalResults) -> list[tuple[str, Job]]:
    """Per-image IoU maps, the IoU scatter and the importances."""
    rules = [r for r in segments.tables if segments.predicted(r, SHOWN_MODEL)]
    if not rules:
        return []
    jobs = []
    examples = []
    for i, (example, maps) in enumerate(zip(results.examples, segments.maps, strict=False)):
        image = example.image.permute(1, 2, 0).numpy()
        for rule in rules:
            table = segments.tables[rule]
            mine = table["image"] == i
            predicted = segments.predicted(rule, SHOWN_MODEL)["iou"][mine]
            tag = f"meta/segments_{i}_{rule}"
            title = f"{rule}: segments of example {i}, IoU predicted by {SHOWN_MODEL}"
            title += f"\n{results.subject}" if results.subject else ""
            examples.append((tag, title, image, maps[rule], table["iou"][mine], predicted))
    if examples:
        jobs.append(("evaluation", job(segment_iou_figures, examples)))
    true = [segments.tables[r]["iou"] for r in rules]
    predicted = {
        m: [segments.predicted(r, m)["iou"] for r in rules]
        for m in ("logistic", "gradient_boosting")
        if all(segments.predicted(r, m) for r in rules)
    }
    jobs.append(("evaluation", job(iou_scatter_figures, rules, true, predicted, results.subject)))
    importances = [segments.models[r].importances(SHOWN_MODEL) for r in rules]
    jobs.append(
        ("evaluation", job(importance_figures, rules, importances, SHOWN_MODEL, results.subject))
    )
    return jobs


def _fusion_jobs(results: EvalResults, fused: GroupResult) -> list[tuple[str, Job]]:
    """The trade-off of each fused rule over τ per fused class × RoI (RoI 1, the street, and
    the whole image): FP segments against missed instances (where measured) and FN segments,
    with the base and the unfused rule marked where they are named rules."""
    if len(fused.group.decide.taus) < 2 or not fused.segments:
        return []
    decider = fused.group.decide
    rows = fused.rows(results.class_ids)
    jobs = []
    for y in ("missed_instances", "fn_segments"):
        panels = []
        for rule in decider.fused:
            for cls in decider.classes:
                for roi in (1, 0):
                    mine = [
                        r for r in rows
                        if r["fused"] == rule.name and r["class"] == CLASS_NAMES[cls]
                        and r["roi"] == roi and y in r
                    ]  # fmt: skip
                    if len(mine) != len(decider.taus):
                        continue
                    marks = _marks(results, (decider.base.name, rule.name), cls, roi, y)
                    title = f"{rule.name}+meta, {CLASS_NAMES[cls]}, RoI {roi}"
                    fp = np.array([r["fp_segments"] for r in mine])
                    panels.append((title, fp, np.array([r[y] for r in mine]), marks))
        if panels:
            args = (panels, list(decider.taus), y.replace("_", " "), results.subject)
            jobs.append(("evaluation", job(tradeoff_figures, *args)))
    return jobs


def _marks(results: EvalResults, rules: tuple[str, ...], cls: int, roi: int, y: str) -> dict:
    """(FP segments, y) of the named rules among ``rules`` for class ``cls`` and RoI ``roi``."""
    rows = [
        r for r in results.named.rows(results.class_ids, [roi])
        if r["matrix"] in rules and r["class"] == CLASS_NAMES[cls] and y in r
    ]  # fmt: skip
    return {r["matrix"]: (r["fp_segments"], r[y]) for r in rows}
