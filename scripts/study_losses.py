"""The losses study of docs/results.md: costs in the loss or in the decision.

    python scripts/study_losses.py [--output_dir study_losses] [--max_steps N]

Trains one model per loss with the demo's recipe (``configs/toy.yaml``, seed 0, the same steps;
each loss a file of ``configs/losses/``), then evaluates each on the toy validation images under
the rules robotistic, altruistic, egoistic and ml, once on the raw probabilities and once on
temperature-scaled ones (the temperature fitted on the toy test split, docs/definitions.md §6).
For the person class in the street RoI it collects precision, recall, instance recall, missed
pedestrians and false-positive / false-negative segments per rule, the rules' mIoU, ECE and NLL,
and each model's training time.

Writes ``study.md`` (the tables of docs/results.md) and ``study.json`` in ``--output_dir``; the
models in ``runs/`` and each evaluation in a subfolder there. A study interrupted after some
models were trained reuses them when run again with the same ``--output_dir``.
"""

from __future__ import annotations

import json
import math
import subprocess
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from costseg.cli import parse_options, user_errors
from costseg.options import option
from costseg.values import whole_number

ROOT = Path(__file__).resolve().parents[1]


@dataclass
class LossStudyOptions:
    """What ``study_losses.py`` can be told (``--help``)."""

    output_dir: Path = option(
        Path("study_losses"),
        "the study's folder (an unfinished study's models are reused)",
        type=Path,
    )
    max_steps: int | None = option(
        help="training steps of each model (default: the recipe's)", type=whole_number(1)
    )


RULES = ["robotistic", "altruistic", "egoistic", "ml"]
TEMPERATURE = ["--calibrate", "temperature", "--calibration_split", "test"]
# name in the tables → the configs/losses/ file composed with toy.yaml (None: its cross-entropy),
# whose name is also the model's folder
LOSSES = {
    "cross-entropy": None,
    "weighted (altruistic)": "weighted_altruistic",
    "focal (γ = 2)": "focal",
    "logit-adjusted (τ = 1, pixel priors)": "logit_adjusted",
    "CE + expected altruistic cost (λ = 1)": "expected_cost_altruistic",
}
PERSON_COLUMNS = ("precision", "recall", "instance_recall", "missed_instances")
SEGMENT_COLUMNS = ("fp_segments", "fn_segments")


def folder_name(name: str) -> str:
    return LOSSES[name] or "cross_entropy"


def train(name: str, runs: Path, max_steps: int | None) -> tuple[Path, float]:
    """Train the model of loss ``name`` (or reuse a finished one); its last.ckpt and seconds."""
    run = runs / folder_name(name)  # runs/ is the save_dir: the models share its priors cache
    done = run / "trained.json"
    if done.is_file():
        record = json.loads(done.read_text())
        return Path(record["checkpoint"]), record["seconds"]
    command = [sys.executable, "train.py", "--config", "toy"]
    if LOSSES[name]:
        command += ["--config", f"losses/{LOSSES[name]}"]
    command += ["--trainer.logger.init_args.save_dir", str(runs)]
    command += ["--trainer.logger.init_args.name", run.name]
    if max_steps is not None:
        command += ["--trainer.max_steps", str(max_steps), "--trainer.val_check_interval"]
        command += [str(max_steps)]
    if last := sorted(run.glob("version_*/checkpoints/last.ckpt")):  # an interrupted training
        command += ["--ckpt_path", str(last[-1])]
    print("$", " ".join(command[1:]), flush=True)
    start = time.perf_counter()
    subprocess.run(command, cwd=ROOT, check=True)
    seconds = time.perf_counter() - start
    checkpoint = sorted(run.glob("version_*/checkpoints/last.ckpt"))[-1].resolve()
    done.write_text(json.dumps({"checkpoint": str(checkpoint), "seconds": seconds}))
    return checkpoint, seconds


def evaluate(checkpoint: Path, options: list[str], output_dir: Path) -> dict:
    """Run evaluate.py on ``checkpoint`` with ``options`` (or reuse its results); results.json."""
    results = output_dir / "results.json"
    if not results.is_file():
        command = [sys.executable, "evaluate.py", "--ckpt_path", str(checkpoint), "--cost", *RULES]
        command += ["--classes", "person", *options, "--output_dir", str(output_dir)]
        command += ["--num_examples", "2", "--no-progress"]
        print("$", " ".join(command[1:]), flush=True)
        subprocess.run(command, cwd=ROOT, check=True)
    return json.loads(results.read_text())


def summary(results: dict) -> dict:
    """What the study keeps of one evaluation: per rule the person street row, mIoU; and the
    calibration of the probabilities decided on (scaled where a temperature was fitted)."""
    rows = {r["matrix"]: r for r in results["rows"] if r["class"] == "person" and r["roi"] == 1}
    keep = (*PERSON_COLUMNS, *SEGMENT_COLUMNS)
    return {
        "person_street": {rule: {k: rows[rule][k] for k in keep} for rule in RULES},
        "miou": results["miou"],
        **{k: list(results[k].values())[-1] for k in ("ece", "nll")},
        "temperature": (results.get("scaling") or {}).get("temperature"),
    }


def _cell(value: float | None, percent: bool) -> str:
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "–"
    return f"{100 * value:.1f}" if percent else f"{value:g}"


def table(models: dict[str, dict], which: str) -> str:
    """One Markdown table, a line per loss and rule, of the ``which`` evaluation (raw / scaled)."""
    lines = [
        "| loss | rule | precision | recall | instance recall | missed | FP seg. | FN seg. "
        "| mIoU | ECE | NLL | training |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for name, model in models.items():
        result = model[which]
        for k, rule in enumerate(RULES):
            row = result["person_street"][rule]
            cells = [_cell(row[c], c != "missed_instances") for c in PERSON_COLUMNS]
            cells += [str(row[c]) for c in SEGMENT_COLUMNS]
            cells.append(f"{100 * result['miou'][rule]:.2f}")
            head = [name, f"{100 * result['ece']:.2f} %", f"{result['nll']:.4f}"]
            head.append(f"{model['train_seconds'] / 60:.1f} min")
            if k:
                head = [""] * 4
            lines.append(f"| {head[0]} | {rule} | {' | '.join(cells)} | {' | '.join(head[1:])} |")
    return "\n".join(lines) + "\n"


def main(args: Sequence[str] | None = None) -> None:
    args = parse_options(LossStudyOptions, args, "study_losses.py", __doc__.splitlines()[0])
    if (args.output_dir / "study.md").exists():
        raise ValueError(f"{args.output_dir} holds a finished study: choose another --output_dir")
    out = args.output_dir.resolve()
    models = {}
    for name in LOSSES:
        checkpoint, seconds = train(name, out / "runs", args.max_steps)
        evaluations = out / "evaluations" / folder_name(name)
        models[name] = {
            "checkpoint": str(checkpoint),
            "train_seconds": seconds,
            "raw": summary(evaluate(checkpoint, [], evaluations / "raw")),
            "scaled": summary(evaluate(checkpoint, TEMPERATURE, evaluations / "scaled")),
        }
    text = "## Raw probabilities\n\n" + table(models, "raw")
    text += "\n## Temperature-scaled probabilities\n\n" + table(models, "scaled")
    (out / "study.md").write_text(text)
    (out / "study.json").write_text(json.dumps(models, indent=2))
    print(text)


if __name__ == "__main__":
    with user_errors(subprocess.CalledProcessError):
        main()
