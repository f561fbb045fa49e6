"""The segment study of docs/results.md: which predicted segments can be trusted, and what fusing
the trusted ones of a rule with argmax does for pedestrians (docs/definitions.md §15).

    python scripts/study_segments.py --ckpt_path A.ckpt [--output_dir study_segments]

Two ``evaluate.py`` runs on the toy validation images, each with meta models fitted on the
segments of ``--meta_images`` training images:

* ``rules/``: the robotistic, altruistic, egoistic and ML rules, with the ML and altruistic rules
  fused with argmax along τ (FUSE_TAUS);
* ``defer/``: the robotistic rule with a defer row of cost DEFER (deferred pixels belong to no
  segment).

Collects the AUROC, accuracy, R² and σ of each meta model per rule, beside the entropy-only
baseline; for person in the street RoI, the missed instances, false-positive segments,
precision and recall of argmax, of each unfused rule and of its fusion at every τ; the τ it
recommends (at most argmax's false-positive segments, then the fewest missed pedestrians, then
the fewest false-positive segments, then the largest τ); and, as MetaFusion's log counts them,
the share of the rule's false person segments (iou0) the classifier drops at that τ and of its
true ones it keeps (over all the rule's person segments in the whole image, candidates or not).
Writes ``study.md`` and ``study.json`` in ``--output_dir``; the fusion curves are the
``rules/figures/fusion_*.png`` of the evaluation.
"""

from __future__ import annotations

import csv
import json
import subprocess
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from costseg.classes import CLASS_NAMES
from costseg.cli import parse_options, user_errors
from costseg.options import option

RULES = ("robotistic", "altruistic", "egoistic", "ml")
FUSED = ("ml", "altruistic")
FUSE_TAUS = tuple(f"{t / 10:g}" for t in range(11))
DEFER = "0.3"
META_IMAGES = "200"
STREET = "1"
PERSON = CLASS_NAMES.index("person")
ROOT = Path(__file__).resolve().parents[1]


@dataclass
class SegmentStudyOptions:
    """What ``study_segments.py`` can be told (``--help``)."""

    ckpt_path: str | None = option(
        help="the network (a costseg checkpoint)", required=True, metavar="PATH"
    )
    output_dir: Path = option(Path("study_segments"), "a new folder for the study", type=Path)


def evaluate(ckpt_path: str, output_dir: Path, *options: str) -> dict:
    """Run evaluate.py with meta models and saved segments; its results.json."""
    command = [sys.executable, "evaluate.py", "--ckpt_path", ckpt_path, *options]
    command += ["--meta", "--meta_split", "train", "--meta_images", META_IMAGES]
    command += ["--save-segments", "--num_examples", "2", "--output_dir", str(output_dir)]
    print("$", " ".join(command[1:]), flush=True)
    subprocess.run(command, cwd=ROOT, check=True)
    return json.loads((output_dir / "results.json").read_text())


def street_person(path: Path) -> list[dict]:
    with open(path, newline="") as f:
        return [r for r in csv.DictReader(f) if r["class"] == "person" and r["roi"] == STREET]


def recommended(plain: dict, curve: list[dict]) -> dict:
    """Among the fused rows with at most ``plain``'s false-positive segments (all rows if none
    has), the one that misses fewest instances; ties to fewer false-positive segments, then to
    the larger τ (more of the rule's segments kept)."""
    fewer = [r for r in curve if int(r["fp_segments"]) <= int(plain["fp_segments"])] or curve
    return min(
        fewer,
        key=lambda r: (int(r["missed_instances"]), int(r["fp_segments"]), -float(r["tau"])),
    )


def classifier_shares(segments_csv: Path, tau: float) -> dict:
    """Of the rule's person segments: the share of the false ones (iou0) whose gradient-boosting
    probability of being false is ≥ τ (dropped) and of the true ones below it (kept)."""
    false, true = [], []
    with open(segments_csv, newline="") as f:
        for row in csv.DictReader(f):
            if int(row["class"]) == PERSON:
                (false if row["iou0"] == "1" else true).append(
                    float(row["gradient_boosting_false"])
                )
    return {
        "false_segments": len(false),
        "false_dropped": sum(p >= tau for p in false) / max(len(false), 1),
        "true_segments": len(true),
        "true_kept": sum(p < tau for p in true) / max(len(true), 1),
    }


def percent(value: float | str) -> str:
    number = float(value)
    return "nan" if number != number else f"{100 * number:.1f}"


def meta_table(scores: dict[str, dict]) -> str:
    lines = [
        "| rule | model | AUROC | accuracy | R² | σ | segments |",
        "|---|---|---|---|---|---|---|",
    ]
    for rule, models in scores.items():
        for model, s in models.items():
            lines.append(
                f"| {rule} | {model} | {percent(s['auroc'])} | {percent(s['accuracy'])} | "
                f"{percent(s['r2'])} | {s['sigma']:.3f} | {s['segments']} |"
            )
    return "\n".join(lines) + "\n"


def fusion_table(plain: dict[str, dict], curves: dict[str, list[dict]]) -> str:
    lines = [
        "| rule | τ | missed pedestrians | FP segments | precision | recall |",
        "|---|---|---|---|---|---|",
    ]

    def line(name: str, tau: str, r: dict) -> str:
        return (
            f"| {name} | {tau} | {r['missed_instances']} of {r['gt_instances']} | "
            f"{r['fp_segments']} | {percent(r['precision'])} | {percent(r['recall'])} |"
        )

    lines.append(line("robotistic (argmax)", "", plain["robotistic"]))
    for rule, curve in curves.items():
        lines.append(line(rule, "unfused", plain[rule]))
        best = recommended(plain["robotistic"], curve)
        for r in curve:
            mark = " (recommended)" if r is best else ""
            lines.append(line(f"{rule}+meta", f"{float(r['tau']):g}{mark}", r))
    return "\n".join(lines) + "\n"


def main(args: Sequence[str] | None = None) -> None:
    args = parse_options(SegmentStudyOptions, args, "study_segments.py", __doc__.splitlines()[0])
    if args.output_dir.exists():
        raise ValueError(f"{args.output_dir} exists: choose another --output_dir")
    if not Path(args.ckpt_path).is_file():
        raise ValueError(f"checkpoint not found: {args.ckpt_path}")
    ckpt_path = str(Path(args.ckpt_path).resolve())
    rules_dir = (args.output_dir / "rules").resolve()
    defer_dir = (args.output_dir / "defer").resolve()
    rules = evaluate(ckpt_path, rules_dir, "--cost", *RULES, "--fuse", *FUSED,
                     "--fuse_tau", *FUSE_TAUS)  # fmt: skip
    defer = evaluate(ckpt_path, defer_dir, "--cost", "robotistic", "--defer", DEFER)
    scores = dict(rules["meta"]["scores"])
    scores[f"robotistic, defer {DEFER}"] = defer["meta"]["scores"]["robotistic"]

    plain = {r["matrix"]: r for r in street_person(rules_dir / "results.csv")}
    fusion = street_person(rules_dir / "fusion.csv")
    curves = {rule: [r for r in fusion if r["fused"] == rule] for rule in FUSED}
    chosen = {rule: recommended(plain["robotistic"], curve) for rule, curve in curves.items()}
    shares = {
        rule: classifier_shares(rules_dir / "segments" / f"{rule}.csv", float(row["tau"]))
        for rule, row in chosen.items()
    }
    text = (
        "Meta models fitted on the segments of "
        f"{rules['meta']['fitted_on']['images']} training images, scored on the validation "
        "images' segments:\n\n"
        + meta_table(scores)
        + "\nPerson in the street RoI, fused with argmax along τ:\n\n"
        + fusion_table(plain, curves)
        + "\nAt the recommended τ, of each rule's person segments in the whole image "
        "(MetaFusion's log):\n\n"
        + "| rule | τ | false segments dropped | true segments kept |\n|---|---|---|---|\n"
        + "".join(
            f"| {rule} | {float(chosen[rule]['tau']):g} | {percent(s['false_dropped'])} % of "
            f"{s['false_segments']} | {percent(s['true_kept'])} % of {s['true_segments']} |\n"
            for rule, s in shares.items()
        )
    )
    (args.output_dir / "study.md").write_text(text)
    (args.output_dir / "study.json").write_text(
        json.dumps(
            {
                "scores": scores,
                "street_person": plain,
                "fusion": curves,
                "recommended": chosen,
                "classifier_shares": shares,
            },
            indent=2,
        )
    )
    print(text)


if __name__ == "__main__":
    with user_errors(subprocess.CalledProcessError):
        main()
