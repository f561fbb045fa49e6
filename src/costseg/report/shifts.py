"""The summary of an evaluation under several shifts (``evaluate.py --shift fog:3 night:2``):
``shifts.md`` and ``shifts.json``, one line per shift (the clean images first) and rule, read
from each evaluation's own ``results.json``: mIoU, the first ``--classes`` class in the street
RoI (precision, recall, instance recall, missed instances) and the calibration of the
probabilities decided on. Units as table.md's and the terminal's: mIoU, precision and recall in
%, ECE and NLL as they are."""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path

from costseg.classes import CLASS_NAMES
from costseg.report.files import write_json, write_text
from costseg.report.tables import markdown_table

COLUMNS = ("precision", "recall", "instance_recall", "missed_instances")
CLEAN = "clean"  # the row and folder of the images without a shift


def shift_rows(folders: dict[str, Path], class_name: str) -> list[dict]:
    """Per shift and rule, what the summary shows (from each folder's results.json)."""
    rows = []
    for shift, folder in folders.items():
        results = json.loads((folder / "results.json").read_text())
        street = {
            r["matrix"]: r for r in results["rows"] if r["class"] == class_name and r["roi"] == 1
        }
        for rule, miou in results["miou"].items():
            row = {"shift": shift, "rule": rule, "miou": miou}
            row |= {f"{class_name} {c}": street.get(rule, {}).get(c) for c in COLUMNS}
            # raw, then scaled where a scaling was fitted: the last is the one decided on
            row |= {k: list(results[k].values())[-1] for k in ("ece", "nll")}
            rows.append(row)
    return rows


def write_shift_summary(out: Path, folders: dict[str, str], class_ids: Sequence[int]) -> None:
    """``shifts.md`` and ``shifts.json`` in ``out``, over the evaluations in ``folders``
    (shift → its folder in ``out``)."""
    class_name = CLASS_NAMES[class_ids[0]]
    rows = shift_rows({shift: out / f for shift, f in folders.items()}, class_name)
    percent = ["miou", *(f"{class_name} {c}" for c in COLUMNS[:3])]
    title = (
        f"# Under shift: {class_name} in the street RoI (RoI 1), per shift and rule\n\n"
        "mIoU, precision, recall and instance recall in %; ECE (top label, 15 bins) and NLL of "
        "the probabilities decided on, as fractions"
    )
    write_text(out / "shifts.md", f"{title}\n\n{markdown_table(rows, percent=percent)}\n")
    write_json(out / "shifts.json", {"class": class_name, "rows": rows})
    print(f"summary over the shifts: {out / 'shifts.md'}")
