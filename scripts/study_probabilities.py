"""The probabilities study of docs/results.md: which probabilities change the cost rules' decisions.

    python scripts/study_probabilities.py --ckpt_path A.ckpt B.ckpt C.ckpt [--output_dir study]

Seven sources of probabilities on the toy validation images, each evaluated by ``evaluate.py``
under the rules robotistic, altruistic, egoistic and ml: the first checkpoint as it is,
temperature-scaled (fitted on the test split, so every row reports the same 100 images), with
flip test-time augmentation, with flip and scales 0.75 / 1 / 1.25, with 8 passes of Monte-Carlo
dropout; the ensemble of all checkpoints, plain and temperature-scaled
(docs/definitions.md §6, §12, §13). For the person class in the street RoI it collects precision,
recall and instance recall per rule, the rules' mIoU and the calibration (ECE, NLL, Brier).

The time per image is the source's probabilities alone (the rules and metrics run once per image
whatever the source), on single images, measured in this process round-robin over the sources
so that a change in the machine's load hits all alike, median over the rounds, ÷ the plain
network's. A temperature adds nothing per image (its fit is a one-off pass over the test split).

Writes ``study.md`` (the table of docs/results.md) and ``study.json`` in ``--output_dir``, and
each source's evaluation in a subfolder.
"""

from __future__ import annotations

import json
import math
import statistics
import subprocess
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import torch

from costseg.cli import parse_options, user_errors
from costseg.data.from_config import build_dataset, image_stems
from costseg.networks.ensemble import open_sources
from costseg.networks.protocols import Protocol
from costseg.options import option
from costseg.values import whole_number

RULES = ["robotistic", "altruistic", "egoistic", "ml"]
TEMPERATURE = ["--calibrate", "temperature", "--calibration_split", "test"]
ROOT = Path(__file__).resolve().parents[1]


def sources(members: list[str]) -> list[tuple[str, list[str], Protocol, int | None]]:
    """(name, evaluate.py options, protocol, Monte-Carlo dropout passes) of each source."""
    first, flip = ["--ckpt_path", members[0]], ["--tta", "flip"]
    scales = (0.75, 1.0, 1.25)
    ensemble = ["--ckpt_path", *members]
    return [
        ("plain", first, Protocol(), None),
        ("temperature-scaled", first + TEMPERATURE, Protocol(), None),
        ("flip TTA", first + flip, Protocol(flip=True), None),
        (
            "multi-scale + flip TTA",
            [*first, *flip, "--scales", *map(str, scales)],
            Protocol(flip=True, scales=scales),
            None,
        ),
        ("MC dropout 8", [*first, "--mc_dropout", "8"], Protocol(), 8),
        (f"ensemble of {len(members)}", ensemble, Protocol(), None),
        (
            f"ensemble of {len(members)}, temperature-scaled",
            ensemble + TEMPERATURE,
            Protocol(),
            None,
        ),
    ]


def evaluate(options: list[str], output_dir: Path) -> dict:
    """Run evaluate.py with ``options``; its results.json."""
    command = [sys.executable, "evaluate.py", "--cost", *RULES, "--classes", "person"]
    command += [*options, "--output_dir", str(output_dir), "--num_examples", "2"]
    print("$", " ".join(command[1:]), flush=True)
    subprocess.run(command, cwd=ROOT, check=True)
    return json.loads((output_dir / "results.json").read_text())


def person_street(results: dict) -> dict[str, list[float]]:
    """Per rule: person precision, recall, instance recall in the street RoI (1), as in the
    rows of results.json."""
    found = {}
    for row in results["rows"]:
        if row["class"] == "person" and row["roi"] == 1:
            found[row["matrix"]] = [row["precision"], row["recall"], row["instance_recall"]]
    return found


def summary(results: dict) -> dict:
    """What the study keeps of one evaluation's results.json."""
    return {
        "person_street": person_street(results),
        "miou": results["miou"],
        # raw, then scaled where a scaling was fitted: the last is the one decided on
        **{k: list(results[k].values())[-1] for k in ("ece", "nll", "brier")},
        "images": results["images"],
        "probabilities": results["probabilities"],
    }


def times_per_image(members: list[str], rounds: int) -> dict[str, float]:
    """Median seconds per image of each distinct (members, protocol, passes) source."""
    device = torch.device("cpu")
    timed = {}
    for name, _, protocol, passes in sources(members):
        if "temperature" in name:
            continue
        paths = members if name.startswith("ensemble") else members[:1]
        timed[name] = open_sources(paths, None, None, device, protocol, passes, seed=0)
    dataset = build_dataset(next(iter(timed.values())).data_config, "val")
    seconds: dict[str, list[float]] = {name: [] for name in timed}
    with torch.inference_mode():
        for r in range(rounds):
            image = dataset[r][0].unsqueeze(0)
            stems = image_stems(dataset, [r])
            for name, source in timed.items():
                start = time.perf_counter()
                source.scores(image, stems)
                seconds[name].append(time.perf_counter() - start)
    return {name: statistics.median(values) for name, values in seconds.items()}


def table(rows: dict[str, dict], ratios: dict[str, float]) -> str:
    """The study's Markdown table: one line per source and rule."""
    lines = [
        "| probabilities | rule | precision | recall | instance recall | mIoU | ECE | NLL | Brier "
        "| time / image |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for name, result in rows.items():
        base = name.replace(", temperature-scaled", "").replace("temperature-scaled", "plain")
        for k, rule in enumerate(RULES):
            p, r, i = (100 * (math.nan if v is None else v) for v in result["person_street"][rule])
            head = [name, f"{result['ece'] * 100:.2f} %", f"{result['nll']:.4f}"]
            head += [f"{result['brier']:.4f}", f"{ratios[base]:.2f}x"]
            if k:
                head = ["", "", "", "", ""]
            lines.append(
                f"| {head[0]} | {rule} | {p:.1f} | {r:.1f} | {i:.1f} | "
                f"{100 * result['miou'][rule]:.2f} | {' | '.join(head[1:])} |"
            )
    return "\n".join(lines) + "\n"


@dataclass
class ProbabilityStudyOptions:
    """What ``study_probabilities.py`` can be told (``--help``)."""

    ckpt_path: list[str] | None = option(
        help="the ensemble's members (costseg checkpoints)", required=True, metavar="PATH"
    )
    output_dir: Path = option(Path("study_probabilities"), "a new folder for the study", type=Path)
    rounds: int = option(10, "images timed per source", type=whole_number(1))


def main(args: Sequence[str] | None = None) -> None:
    args = parse_options(
        ProbabilityStudyOptions, args, "study_probabilities.py", __doc__.splitlines()[0]
    )
    if args.output_dir.exists():
        raise ValueError(f"{args.output_dir} exists: choose another --output_dir")
    for path in args.ckpt_path:
        if not Path(path).is_file():
            raise ValueError(f"checkpoint not found: {path}")
    members = [str(Path(p).resolve()) for p in args.ckpt_path]
    rows = {}
    for name, options, _, _ in sources(members):
        folder = args.output_dir / name.replace(" ", "_").replace(",", "")
        results = evaluate(options, folder.resolve())
        rows[name] = summary(results)
    torch.set_num_threads(1)
    ratios = times_per_image(members, args.rounds)
    ratios = {name: seconds / ratios["plain"] for name, seconds in ratios.items()}
    text = table(rows, ratios)
    (args.output_dir / "study.md").write_text(text)
    (args.output_dir / "study.json").write_text(
        json.dumps({"sources": rows, "time_ratio": ratios}, indent=2)
    )
    print(text)


if __name__ == "__main__":
    with user_errors(subprocess.CalledProcessError):
        main()
