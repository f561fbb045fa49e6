"""The named rules' outputs (``--cost``) and every rule family's: the paper's table in
``table.md`` next to the paper's numbers, ``results.csv``, the rows and confusion matrices of
``results.json``, the FP / FN maps, and each family's own outputs
(:mod:`costseg.report.families`)."""

from __future__ import annotations

from typing import Any

from costseg.classes import CLASS_NAMES, ROI_NAMES
from costseg.metrics.names import DEFER_RULE_RATES, ERROR_COLUMNS, INSTANCE_COLUMNS
from costseg.report.calibration import CalibrationOutputs, calibration_line
from costseg.report.drawing import Job, job
from costseg.report.families import family_sections
from costseg.report.figures import heatmap_grid_figures
from costseg.report.files import write_csv
from costseg.report.results import EvalResults, GroupResult, GroupResults
from costseg.report.sections import Result, Section, merge
from costseg.report.tables import (
    PAPER_COLUMNS,
    PAPER_ROIS,
    compare_with_paper,
    console_table,
    format_value,
    markdown_table,
    paper_table,
)
from costseg.rules import DEFER_COLUMN

SUMMARY_COLUMNS = (*PAPER_COLUMNS, *ERROR_COLUMNS)
DEFER_SUMMARY = (DEFER_COLUMN, "coverage", "handled_recall", *DEFER_RULE_RATES)
"""The console's columns of deferral, where a named rule defers (table.md and the files hold
every column)."""


class GroupOutputs(GroupResults, Result):
    """The metrics of every rule group, written: the named rules' headline, then each family's
    outputs."""

    def write(self, results: EvalResults) -> Section:
        """``results.csv``, the headline of table.md and results.json, the FP / FN maps, each
        family's files, and ``best.json`` for ``--target``."""
        named = results.named
        rows = named.rows(results.class_ids)
        shown = [named, *(g for g in results.groups if g.group.headline)]
        rois = tuple(sorted({*PAPER_ROIS, *results.rois}))
        headline = [r for g in shown for r in g.rows(results.class_ids, rois)]
        instances = INSTANCE_COLUMNS[:2] if named.instances else ()
        deferral = DEFER_SUMMARY if any(g.group.defers for g in shown) else ()
        mious = {n: v for g in shown for n, v in _miou(g).items()}
        write_csv(results.output_dir / "results.csv", rows)
        section = Section(
            json=_json(named, rows) | {"instances": self.instances},
            table=_tables(headline, shown, rois, self._probability_note(results)),
            console=[
                console_table(headline, (*SUMMARY_COLUMNS, *deferral, *instances)),
                "mIoU: " + ", ".join(f"{n} {100 * v:.2f}" for n, v in mious.items()),
            ],
            tables={"evaluation/results": markdown_table(rows)},
            jobs=[("evaluation", _fp_fn_figures(results))],
        )
        return merge([section, *family_sections(results)])

    def _probability_note(self, results: EvalResults) -> str:
        calibration = results.find(CalibrationOutputs)
        rows = calibration.rows() if calibration else []
        note = results.probabilities + (f"; {calibration_line(rows)}" if rows else "")
        if loss := training_loss(results.source):
            note += f"; the network was trained with {loss}"
        return f"{note}. {self.instances}"


def training_loss(source: dict[str, Any]) -> str | None:
    """The loss a costseg checkpoint records (docs/definitions.md §16) as ``Name(arg=value)``,
    or None.

    >>> training_loss({"hparams": {"loss": {"class_path": "m.FocalLoss",
    ...                                     "init_args": {"gamma": 2.0}}}})
    'FocalLoss(gamma=2.0)'
    """
    entry = (source.get("hparams") or {}).get("loss")
    if not entry:
        return None
    args = ", ".join(f"{k}={v}" for k, v in entry.get("init_args", {}).items() if v is not None)
    return f"{entry['class_path'].rpartition('.')[2]}({args})"


def _miou(result: GroupResult) -> dict[str, float]:
    return {n: result.pixels["miou"][k].item() for k, n in enumerate(result.group.names)}


def _tables(
    headline: list[dict], shown: list[GroupResult], rois: tuple[int, ...], probabilities: str
) -> str:
    named = set(shown[0].group.names)  # the paper compares the --cost rules only
    where = ", ".join(f"{r} = {ROI_NAMES[r]}" for r in rois)
    return "\n\n".join(
        [
            f"# Precision and recall per cost matrix (RoI {where})",
            f"Probabilities: {probabilities}.",
            paper_table(headline),
            _miou_table(shown),
            "## Next to the paper (Cityscapes val, DeepLabv3+ Xception)",
            compare_with_paper([r for r in headline if r["matrix"] in named]) + "\n",
        ]
    )


def _miou_table(shown: list[GroupResult]) -> str:
    """The mIoU of each named rule (and of each group shown beside them: a designed one);
    where one defers, its defer cost and the share of the image's pixels it deferred (a
    deferred pixel is a false negative of its class in IoU)."""
    if not any(g.group.defers for g in shown):
        miou = "\n".join(f"| {n} | {100 * v:.2f} |" for g in shown for n, v in _miou(g).items())
        return f"## mIoU (19 classes)\n\n| matrix | mIoU |\n|---|---|\n{miou}"
    lines = [
        f"| {name} | {format_value(g.group.rules[k].defer_cost if g.group.rules else None)} | "
        f"{100 * miou:.2f} | {format_value(_deferred(g, k), percent=True)} |"
        for g in shown
        for k, (name, miou) in enumerate(_miou(g).items())
    ]
    return (
        "## mIoU (19 classes; a deferred pixel is a false negative of its class)\n\n"
        "| matrix | defer | mIoU | deferred (whole image) |\n|---|---|---|---|\n" + "\n".join(lines)
    )


def _deferred(result: GroupResult, k: int) -> float | None:
    """The share of the image's pixels rule k deferred (None: its group never defers)."""
    return result.pixels["deferred_rate"][k, 0].item() if result.group.defers else None


def _json(named: GroupResult, rows: list[dict]) -> dict:
    pixels, names = named.pixels, named.group.names
    return {
        "rows": rows,
        "miou": _miou(named),
        "iou": {
            n: dict(zip(CLASS_NAMES, pixels["iou"][k].tolist(), strict=False))
            for k, n in enumerate(names)
        },
        "confusion_matrix": {
            "layout": "[rule][true class][predicted class], whole image, pixels"
            + (" not deferred" if named.group.defers else ""),
            **{n: pixels["confmat"][k, 0].tolist() for k, n in enumerate(names)},
        },
        **_deferral_json(named),
    }


def _deferral_json(named: GroupResult) -> dict:
    """Where a named rule defers: each rule's defer cost (null: it never defers) and its
    deferred pixels per true class."""
    if not named.group.defers:
        return {}
    names = named.group.names
    return {
        "defer": {r.name: r.defer_cost for r in named.group.rules},
        "deferred_pixels": {
            "layout": "[rule][true class], whole image, pixels deferred",
            **{n: named.pixels["deferred"][k, 0].tolist() for k, n in enumerate(names)},
        },
    }


def _fp_fn_figures(results: EvalResults) -> Job:
    """The named rules' FP / FN segment maps (and missed instances), undrawn: figures of one
    kind are one figure redrawn."""
    named = results.named
    names, segments, instances = named.group.names, named.segments, named.instances
    grids = []
    for kind, key in (("FP", "fp_map"), ("FN", "fn_map")):
        maps = {
            (n, CLASS_NAMES[cls]): segments[key][k, c]
            for k, n in enumerate(names)
            for c, cls in enumerate(results.class_ids)
        }
        grids.append((f"{kind.lower()}_segments", maps, kind))
    if instances and instances["missed_map"].shape[-1] > 0:
        maps = {
            (n, CLASS_NAMES[cls]): instances["missed_map"][k, c]
            for k, n in enumerate(names)
            for c, cls in enumerate(instances["classes"].tolist())
        }
        grids.append(("missed_instances", maps, "missed instances"))
    return job(heatmap_grid_figures, grids, results.subject)
