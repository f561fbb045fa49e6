"""The shift study of docs/results.md: does what holds on clean images hold under shift?

    python scripts/study_shift.py --ckpt_path A.ckpt B.ckpt C.ckpt [--output_dir study_shift]

Two sources of probabilities on the 100 toy validation images: the first checkpoint, and the
temperature-scaled ensemble of all of them (T fitted on the clean toy test split). Each is
evaluated by one ``evaluate.py --shift ...`` run, clean and through every corruption of
``SHIFTS`` at severities 1, 3 and 5 (docs/definitions.md §17), under the robotistic, altruistic
and egoistic rules and the robotistic rule with a defer row of cost 0.3: per shift and rule
mIoU, person precision, recall and missed pedestrians in the street RoI, ECE and NLL.

Unknown objects: ``evaluate.py --anomalies`` on the first checkpoint, clean and through each
corruption at severity 3: AUROC, AP, FPR95, sIoU, PPV and mean F1 of every anomaly score.

The guarantee: ``check_guarantee.py`` on the first checkpoint certifies a point of the triangle
(``--sweep 0.1``, person recall in the street RoI >= 0.9 at δ = 0.1, best precision) on clean
calibration sets and counts how often the certified choice violates the target on each shifted
test set (``--trials`` sets of ``--n`` images).

Writes ``study.md`` (the tables of docs/results.md), ``study.json`` and ``shift_severity.png``
(each metric against severity, one line per rule) in ``--output_dir``, each run in a subfolder;
a run whose results exist is not repeated.
"""

from __future__ import annotations

import json
import math
import subprocess
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from matplotlib.figure import Figure

from costseg.cli import parse_options, user_errors
from costseg.data.shift import parse_shift
from costseg.evaluation.shifts import shift_folder
from costseg.options import SourceOptions, option, same_option
from costseg.report.files import save_figure
from costseg.values import whole_number

ROOT = Path(__file__).resolve().parents[1]
SHIFTS = ("fog", "night", "gaussian_noise", "motion_blur", "jpeg")
SEVERITIES = (1, 3, 5)
CLEAN = "fog:0"  # severity 0 of any corruption is the clean image
DEFER = "robotistic_defer"
RULES = ("robotistic", "altruistic", "egoistic", DEFER)
TARGET = ["--sweep", "0.1", "--target", "person:roi1:recall>=0.9"]
TARGET += ["--maximize", "person:roi1:precision", "--guarantee", "0.1"]


@dataclass
class ShiftStudyOptions:
    """What ``study_shift.py`` can be told (``--help``)."""

    ckpt_path: list[str] | None = option(
        help="the ensemble's members (costseg checkpoints)", required=True, metavar="PATH"
    )
    output_dir: Path = option(
        Path("study_shift"), "the study's folder (runs with results are kept)", type=Path
    )
    n: int = option(50, "images per calibration set", type=whole_number(1))
    trials: int = option(40, "calibration sets", type=whole_number(1))
    test: int = option(300, "test images per shift", type=whole_number(1))
    limit: int | None = same_option(
        SourceOptions, "limit", help="validation images per evaluation (all: 100)"
    )


def all_shifts() -> list[str]:
    return [CLEAN, *(f"{name}:{s}" for name in SHIFTS for s in SEVERITIES)]


def run(script: str, options: list[str], done: Path) -> None:
    """``script`` with ``options`` unless ``done`` exists."""
    if done.is_file():
        return
    command = [sys.executable, script, *options]
    print("$", " ".join(command[1:]), flush=True)
    subprocess.run(command, cwd=ROOT, check=True)


def evaluate(options: list[str], out: Path, shifts: list[str], limit: int | None) -> list[dict]:
    """The rows of shifts.json of one evaluate.py run over ``shifts``."""
    args = ["--shift", *shifts, "--classes", "person", "--num_examples", "1", "--no-progress"]
    args += [] if limit is None else ["--limit", str(limit)]
    run("evaluate.py", [*options, *args, "--output_dir", str(out)], out / "shifts.json")
    return json.loads((out / "shifts.json").read_text())["rows"]


def anomaly_rows(ckpt: str, out: Path, limit: int | None) -> dict[str, dict]:
    """shift → score → metrics, from one ``--anomalies`` run."""
    shifts = [CLEAN, *(f"{name}:3" for name in SHIFTS)]
    evaluate(["--ckpt_path", ckpt, "--cost", "robotistic", "altruistic", "egoistic",
              "--anomalies"], out, shifts, limit)  # fmt: skip
    found = {}
    for shift in shifts:
        results = json.loads((out / shift_folder(parse_shift(shift)) / "results.json").read_text())
        found[shift] = results["anomalies"]["scores"]
    return found


def guarantee(ckpts: list[str], out: Path, args: ShiftStudyOptions) -> dict:
    """Violation rates of Learn-then-Test and of the naive choice, clean and per shift."""
    options = ["--ckpt_path", ckpts[0], *TARGET, "--n", str(args.n), "--trials", str(args.trials)]
    options += ["--test", str(args.test), "--output_dir", str(out), "--shift", *all_shifts()[1:]]
    run("scripts/check_guarantee.py", options, out / "guarantee_check.json")
    found = json.loads((out / "guarantee_check.json").read_text())
    rates = {CLEAN: {r: found[r]["violation_rate"] for r in ("ltt", "naive")}}
    for shift, under in found["shifts"].items():
        rates[shift] = {r: under[r]["violation_rate"] for r in ("ltt", "naive")}
    return rates


def _percent(value: float | None) -> str:
    return (
        "–"
        if value is None or (isinstance(value, float) and math.isnan(value))
        else f"{100 * value:.1f}"
    )


def rules_table(sources: dict[str, list[dict]], rates: dict[str, dict]) -> str:
    """A line per source, shift and rule; the guarantee's violation rates beside the first."""
    head = "| probabilities | shift | rule | mIoU | precision | recall | missed | ECE | NLL "
    lines = [head + "| LTT violates | naive violates |", "|---|" * 1 + "---|" * 10]
    for k, (source, rows) in enumerate(sources.items()):
        for i, row in enumerate(rows):
            first = row["rule"] == RULES[0]
            shift = "clean" if row["shift"] == CLEAN else row["shift"]
            missed = row["person missed_instances"]
            cells = [source if i == 0 else "", shift if first else "", row["rule"]]
            cells += [f"{100 * row['miou']:.2f}", _percent(row["person precision"])]
            cells += [_percent(row["person recall"]), "–" if missed is None else str(missed)]
            cells += [f"{100 * row['ece']:.2f} %", f"{row['nll']:.3f}"] if first else ["", ""]
            rate = rates.get(row["shift"]) if k == 0 and first else None
            cells += [_percent(rate["ltt"]), _percent(rate["naive"])] if rate else ["", ""]
            lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def anomaly_table(found: dict[str, dict]) -> str:
    """A line per shift and score: AUROC, AP, FPR95, sIoU, PPV, mean F1."""
    lines = ["| shift | score | AUROC | AP | FPR95 | sIoU | PPV | mean F1 |",
             "|---|---|---|---|---|---|---|---|"]  # fmt: skip
    for shift, scores in found.items():
        for k, (name, m) in enumerate(scores.items()):
            label = ("clean" if shift == CLEAN else shift) if k == 0 else ""
            values = [_percent(m[c]) for c in ("auroc", "ap", "fpr95", "siou", "ppv", "mean_f1")]
            lines.append(f"| {label} | {name} | {' | '.join(values)} |")
    return "\n".join(lines) + "\n"


def plot(rows: list[dict], path: Path) -> None:
    """Each metric against severity (0 = clean), a panel per corruption, a line per rule."""
    metrics = (("miou", "mIoU"), ("person recall", "person recall (street)"),
               ("person missed_instances", "pedestrians missed"), ("ece", "ECE"))  # fmt: skip
    fig = Figure(figsize=(3.2 * len(SHIFTS), 2.6 * len(metrics)), layout="constrained")
    axes = fig.subplots(len(metrics), len(SHIFTS), sharex=True, sharey="row")
    by = {(r["shift"], r["rule"]): r for r in rows}
    for c, name in enumerate(SHIFTS):
        for m, (key, label) in enumerate(metrics):
            ax = axes[m, c]
            for rule in RULES[:1] if key == "ece" else RULES:
                shifts = [CLEAN, *(f"{name}:{s}" for s in SEVERITIES)]
                values = [by[(s, rule)][key] for s in shifts]
                values = [math.nan if v is None else v for v in values]
                ax.plot([0, *SEVERITIES], values, marker="o", label=rule)
            ax.set_title(name if m == 0 else "")
            ax.set_ylabel(label if c == 0 else "")
            ax.set_xlabel("severity" if m == len(metrics) - 1 else "")
    axes[0, -1].legend(fontsize=7)
    save_figure(fig, path)


def main(args: Sequence[str] | None = None) -> None:
    args = parse_options(ShiftStudyOptions, args, "study_shift.py", __doc__.splitlines()[0])
    if (args.output_dir / "study.md").exists():
        raise ValueError(f"{args.output_dir} holds a finished study: choose another --output_dir")
    for path in args.ckpt_path:
        if not Path(path).is_file():
            raise ValueError(f"checkpoint not found: {path}")
    out, ckpts = args.output_dir.resolve(), [str(Path(p).resolve()) for p in args.ckpt_path]
    out.mkdir(parents=True, exist_ok=True)
    (out / f"{DEFER}.yaml").write_text(f"name: {DEFER}\noff_diagonal: 1\ndefer: 0.3\n")
    rules = ["--cost", *RULES[:3], str(out / f"{DEFER}.yaml")]
    scaled = ["--calibrate", "temperature", "--calibration_split", "test"]
    sources = {
        "plain": evaluate(
            ["--ckpt_path", ckpts[0], *rules], out / "plain", all_shifts(), args.limit
        ),
        f"ensemble of {len(ckpts)}, temperature-scaled": evaluate(
            ["--ckpt_path", *ckpts, *rules, *scaled], out / "ensemble", all_shifts(), args.limit
        ),
    }
    unknown = anomaly_rows(ckpts[0], out / "anomalies", args.limit)
    rates = guarantee(ckpts, out / "guarantee", args)
    text = "## Rules under shift\n\n" + rules_table(sources, rates)
    text += "\n## Unknown objects\n\n" + anomaly_table(unknown)
    (out / "study.md").write_text(text)
    record = {"sources": sources, "anomalies": unknown, "guarantee_violations": rates}
    (out / "study.json").write_text(json.dumps(record, indent=2))
    plot(sources["plain"], out / "shift_severity.png")
    print(text)


if __name__ == "__main__":
    with user_errors(subprocess.CalledProcessError):
        main()
