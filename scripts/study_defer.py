"""The defer study of docs/results.md: what a cost for deferring changes for pedestrians.

    python scripts/study_defer.py --ckpt_path A.ckpt [--output_dir study_defer]

For the robotistic, altruistic and egoistic rules, one ``evaluate.py --defer_sweep`` each on
the toy validation images, over defer costs that span the rule's own scale (its off-diagonal
costs run from 1 to 1, 0.1 to 1000 and 0.1 to 1000: RANGES). In the street RoI it collects the
coverage over all classes and, for the person class, coverage, selective precision (= precision)
and recall, handled recall and the instances missed, beside the rule without a defer row (the
named rules of the same run), at the smallest defer cost whose coverage over all classes reaches
90 %, 95 % and 99 % (docs/definitions.md §14).

Writes ``study.md`` (the table), ``study.json`` and ``risk_coverage.png`` (street RoI: selective
error against coverage over all classes; person handled and selective recall against person
coverage; one curve per rule) in ``--output_dir``, and each rule's evaluation in a subfolder.
"""

from __future__ import annotations

import csv
import json
import subprocess
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from costseg.cli import parse_options, user_errors
from costseg.options import option

RANGES = {
    "robotistic": ("0", "1", "0.02"),
    "altruistic": ("0", "20", "0.2"),
    "egoistic": ("0", "50", "0.5"),
}
"""START STOP STEP of each rule's sweep."""
COVERAGES = (0.90, 0.95, 0.99)
"""The street RoI's coverage over all classes at which the table reads each curve."""
STREET = "1"
ROOT = Path(__file__).resolve().parents[1]


@dataclass
class DeferStudyOptions:
    """What ``study_defer.py`` can be told (``--help``)."""

    ckpt_path: str | None = option(
        help="the network (a costseg checkpoint)", required=True, metavar="PATH"
    )
    output_dir: Path = option(Path("study_defer"), "a new folder for the study", type=Path)


def sweep(ckpt_path: str, rule: str, output_dir: Path) -> tuple[list[dict], dict]:
    """Run evaluate.py's defer sweep of ``rule``: (person rows of the sweep in the street RoI,
    the person row of the rule without deferral)."""
    command = [sys.executable, "evaluate.py", "--ckpt_path", ckpt_path, "--cost", rule]
    command += ["--classes", "person", "--defer_sweep", *RANGES[rule]]
    command += ["--output_dir", str(output_dir), "--num_examples", "2"]
    print("$", " ".join(command[1:]), flush=True)
    subprocess.run(command, cwd=ROOT, check=True)

    def street_person(name: str) -> list[dict]:
        with open(output_dir / name, newline="") as f:
            rows = list(csv.DictReader(f))
        return [r for r in rows if r["class"] == "person" and r["roi"] == STREET]

    return street_person("defer_sweep.csv"), street_person("results.csv")[0]


def number(text: str) -> float:
    return float("nan") if text in ("", "nan") else float(text)


def reading(rows: list[dict], plain: dict, coverage: float) -> dict | None:
    """The row of the smallest defer cost whose coverage over all classes reaches ``coverage``
    (None if none does), with the instances it keeps from being missed."""
    for row in sorted(rows, key=lambda r: number(r["defer"])):
        if number(row["coverage_all_classes"]) >= coverage:
            kept = int(plain["missed_instances"]) - int(row["missed_instances"])
            return {**row, "deferred_not_missed": kept}
    return None


def percent(text) -> str:
    value = number(str(text))
    return "nan" if value != value else f"{100 * value:.1f}"


def table(curves: dict[str, tuple[list[dict], dict]]) -> str:
    """The study's Markdown table: per rule, no deferral then each coverage of COVERAGES."""
    lines = [
        "| rule | defer cost | coverage, all classes | person coverage | precision | selective "
        "recall | handled recall | instances missed | deferred, not missed |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for rule, (rows, plain) in curves.items():
        lines.append(
            f"| {rule} | none | 100.0 | 100.0 | {percent(plain['precision'])} | "
            f"{percent(plain['recall'])} | {percent(plain['recall'])} | "
            f"{plain['missed_instances']} of {plain['gt_instances']} | 0 |"
        )
        for coverage in COVERAGES:
            row = reading(rows, plain, coverage)
            if row is None:
                lines.append(f"|  | (coverage {coverage:.0%} not reached) | | | | | | | |")
                continue
            lines.append(
                f"|  | {number(row['defer']):g} | {percent(row['coverage_all_classes'])} | "
                f"{percent(row['coverage'])} | {percent(row['precision'])} | "
                f"{percent(row['selective_recall'])} | {percent(row['handled_recall'])} | "
                f"{row['missed_instances']} of {row['gt_instances']} | "
                f"{row['deferred_not_missed']} |"
            )
    return "\n".join(lines) + "\n"


def figure(curves: dict[str, tuple[list[dict], dict]], path: Path) -> None:
    """Two panels, one curve per rule: selective error against coverage over all classes; person
    handled recall (solid) and selective recall (dashed) against person coverage."""
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib import pyplot as plt

    fig, (left, right) = plt.subplots(1, 2, figsize=(11, 4.2), constrained_layout=True)
    for k, (rule, (rows, _)) in enumerate(curves.items()):
        colour = f"C{k}"
        x = [number(r["coverage_all_classes"]) for r in rows]
        left.plot(x, [number(r["selective_error_all_classes"]) for r in rows], ".-", c=colour)
        left.plot([], [], ".-", c=colour, label=f"{rule} (defer {' to '.join(RANGES[rule][:2])})")
        x = [number(r["coverage"]) for r in rows]
        right.plot(x, [number(r["handled_recall"]) for r in rows], ".-", c=colour, label=rule)
        right.plot(x, [number(r["selective_recall"]) for r in rows], ".--", c=colour)
    left.set(
        xlabel="coverage, all classes (share of the RoI's pixels not deferred)",
        ylabel="selective error (wrong among those not deferred)",
        title="street RoI: risk against coverage",
    )
    right.set(
        xlabel="person coverage (share of person pixels not deferred)",
        ylabel="person recall",
        title="person, street RoI: handled — and selective - - recall",
    )
    for axes in (left, right):
        axes.grid(alpha=0.3)
        axes.legend(fontsize=8)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(args: Sequence[str] | None = None) -> None:
    args = parse_options(DeferStudyOptions, args, "study_defer.py", __doc__.splitlines()[0])
    if args.output_dir.exists():
        raise ValueError(f"{args.output_dir} exists: choose another --output_dir")
    for path in [args.ckpt_path]:
        if not Path(path).is_file():
            raise ValueError(f"checkpoint not found: {path}")
    ckpt_path = str(Path(args.ckpt_path).resolve())
    curves = {rule: sweep(ckpt_path, rule, (args.output_dir / rule).resolve()) for rule in RANGES}
    text = table(curves)
    (args.output_dir / "study.md").write_text(text)
    (args.output_dir / "study.json").write_text(
        json.dumps({"ranges": RANGES, "curves": curves}, indent=2)
    )
    figure(curves, args.output_dir / "risk_coverage.png")
    print(text)


if __name__ == "__main__":
    with user_errors(subprocess.CalledProcessError):
        main()
