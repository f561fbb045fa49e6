"""The monitor study of docs/results.md: a certified matrix against the run-time monitor on a
stream whose conditions change mid-way (docs/definitions.md §22).

    python scripts/study_monitor.py --ckpt_path last.ckpt [--output_dir study_monitor]

For each requirement set of ``SETS`` (three requirements in different RoIs, and one street
recall target): a matrix designed in the Lagrangian space and certified by Pareto Testing
(``evaluate.py --design lagrangian``, δ = ``--delta``) on the clean ``--design_split`` images;
then the reported images as a stream (``--frames`` of them in order), clean up to ``--onset``
and through each shift of ``SHIFTS`` after it (``evaluate.py --monitor_require ...
--monitor_start designed_cost.yaml --shift ... --shift_onset``, the probabilities saved), with
the first ``--eta`` and ``--delay``; each other step size (at the first delay) and each other
delay (at the first step size) replays the saved probabilities (``--probs``): the same frames,
no network. Per set, shift, η and delay: the fixed
(certified) matrix's long-run risk and the monitored one's against α and the bound, both after
the onset, the share of 50-frame windows above α, and the agreement with argmax.

Writes ``study.md`` (the tables of docs/results.md) and ``study.json`` in ``--output_dir``, each
run in a subfolder; a run whose results exist is not repeated.
"""

from __future__ import annotations

import csv
import json
import math
import subprocess
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from costseg.cli import parse_options, user_errors
from costseg.data.shift import parse_shift
from costseg.evaluation.shifts import shift_folder
from costseg.options import option
from costseg.values import fraction, positive_number, whole_number

ROOT = Path(__file__).resolve().parents[1]
SETS = {
    "three requirements": [
        "person:roi1:recall>=0.8", "building:roi3:precision>=0.8", "car:roi1:recall>=0.7",
    ],
    "street recall": ["person:roi1:recall>=0.8"],
}  # fmt: skip
SHIFTS = ("fog:3", "motion_blur:3", "night:1")


@dataclass
class MonitorStudyOptions:
    """What ``study_monitor.py`` can be told (``--help``)."""

    ckpt_path: str | None = option(help="a costseg checkpoint", required=True, metavar="PATH")
    output_dir: Path = option(
        Path("study_monitor"), "the study's folder (runs with results are kept)", type=Path
    )
    frames: int | None = option(help="frames of the stream (default 100: the toy validation split)",
                                type=whole_number(2))  # fmt: skip
    onset: int | None = option(help="clean frames before the shift (default: half the stream)",
                               type=whole_number(1))  # fmt: skip
    eta: list[float] = option([0.5, 0.1, 2.0], "step sizes η (the first: the main run)",
                              type=positive_number)  # fmt: skip
    delay: list[int] = option([0, 10], "label delays in frames (the first: the main run)",
                              type=whole_number(0))  # fmt: skip
    delta: float = option(0.1, "δ of the certified design", type=fraction)
    design_split: str = option("test", "the clean split the design is certified on")


def run(options: list[str], done: Path) -> None:
    """``evaluate.py`` with ``options`` unless ``done`` exists."""
    if done.is_file():
        return
    command = [sys.executable, "evaluate.py", *options, "--no-progress", "--num_examples", "0"]
    print("$", " ".join(command[1:]), flush=True)
    subprocess.run(command, cwd=ROOT, check=True)


def design(ckpt: str, require: list[str], out: Path, args: MonitorStudyOptions) -> Path | None:
    """The certified designed matrix's file (None: nothing certified)."""
    run(["--ckpt_path", ckpt, "--cost", "robotistic", "--design", "lagrangian", "--require",
         *require, "--design_delta", str(args.delta), "--calibration_split", args.design_split,
         "--output_dir", str(out)], out / "design.json")  # fmt: skip
    found = out / "designed_cost.yaml"
    return found if found.is_file() else None


def summary(folder: Path, onset: int) -> dict:
    """One stream's figures, from its results.json and monitor.csv."""
    record = json.loads((folder / "results.json").read_text())["monitor"]
    rows = list(csv.DictReader((folder / "monitor.csv").open()))
    out = {"agreement": record["agreement"], "requirements": {}}
    for text, r in record["requirements"].items():
        after = {
            kind: _mean([float(row[f"{prefix}loss {text}"]) for row in rows[onset:]])
            for kind, prefix in (("fixed", "fixed "), ("monitored", ""))
        }
        out["requirements"][text] = {
            "alpha": r["alpha"], "fixed": r["fixed_risk"], "monitored": r["monitored_risk"],
            "bound": r["bound"], "after_onset": after, "windows": r["windows_above_alpha"],
            "mu_start": r["mu_start"], "mu_end": r["mu_end"],
            "capped_steps": r["capped_steps"],
        }  # fmt: skip
    return out


def stream(ckpt: str, require: list[str], start: Path | None, out: Path, frames: int,
           args: MonitorStudyOptions, onset: int) -> dict:  # fmt: skip
    """Every shift's summary at each η and delay run: ``{shift: {(η, d): summary}}``."""
    monitor = ["--cost", "robotistic", "--monitor_require", *require, "--limit", str(frames)]
    monitor += [] if start is None else ["--monitor_start", str(start)]
    main = out / "main"
    run(["--ckpt_path", ckpt, *monitor, "--shift", *SHIFTS, "--shift_onset", str(onset),
         "--save-probs", "--monitor_eta", str(args.eta[0]), "--monitor_delay",
         str(args.delay[0]), "--output_dir", str(main)], main / "shifts.json")  # fmt: skip
    found = {}
    for shift in ("clean", *SHIFTS):
        folder = shift if shift == "clean" else shift_folder(parse_shift(shift))
        found[shift] = {(args.eta[0], args.delay[0]): summary(main / folder, onset)}
        varied = [(eta, args.delay[0]) for eta in args.eta[1:]]
        varied += [(args.eta[0], delay) for delay in args.delay[1:]]
        for eta, delay in varied:
            again = out / f"eta{eta:g}_delay{delay}" / folder
            run(["--probs", str(main / folder / "probs"), *monitor, "--monitor_eta", str(eta),
                 "--monitor_delay", str(delay), "--output_dir", str(again)],
                again / "results.json")  # fmt: skip
            found[shift][(eta, delay)] = summary(again, onset)
    return found


def table(name: str, start: Path | None, found: dict, onset: int, frames: int) -> str:
    """A line per shift, η, delay and requirement."""
    head = (f"### {name} ({frames} frames, shift from frame {onset + 1}; start: "
            f"{'the certified matrix' if start else 'C0 (nothing certified)'})\n\n")  # fmt: skip
    lines = [
        "| shift | η | delay | requirement | α | fixed risk | monitored risk | bound | fixed "
        "after onset | monitored after onset | windows above α, fixed | windows above α, "
        "monitored | μ start → end | agreement fixed | agreement monitored |",
        "|---" * 15 + "|",
    ]
    for shift, runs in found.items():
        for (eta, delay), s in runs.items():
            for i, (text, r) in enumerate(s["requirements"].items()):
                first = i == 0
                cells = [shift, f"{eta:g}", str(delay)] if first else ["", "", ""]
                cells += [text, f"{r['alpha']:.2g}", _cell(r["fixed"]), _cell(r["monitored"])]
                cells += [_cell(r["bound"]), _cell(r["after_onset"]["fixed"])]
                cells += [_cell(r["after_onset"]["monitored"])]
                cells += [_percent(r["windows"]["fixed"]), _percent(r["windows"]["monitored"])]
                cells += [f"{r['mu_start']:.3g} → {r['mu_end']:.3g}"]
                agree = s["agreement"]
                cells += [_cell(agree["fixed"]), _cell(agree["monitored"])] if first else ["", ""]
                lines.append("| " + " | ".join(cells) + " |")
    return head + "\n".join(lines) + "\n"


def _mean(values: list[float]) -> float | None:
    kept = [v for v in values if not math.isnan(v)]
    return sum(kept) / len(kept) if kept else None


def _cell(value: float | None) -> str:
    return "–" if value is None else f"{value:.3f}"


def _percent(value: float | None) -> str:
    return "–" if value is None or math.isnan(value) else f"{100 * value:.0f} %"


def main(args: Sequence[str] | None = None) -> None:
    args = parse_options(MonitorStudyOptions, args, "study_monitor.py", __doc__.splitlines()[0])
    if not Path(args.ckpt_path).is_file():
        raise ValueError(f"checkpoint not found: {args.ckpt_path}")
    if (args.output_dir / "study.md").exists():
        raise ValueError(f"{args.output_dir} holds a finished study: choose another --output_dir")
    out, ckpt = args.output_dir.resolve(), str(Path(args.ckpt_path).resolve())
    frames = args.frames or 100
    onset = args.onset if args.onset is not None else frames // 2
    if onset >= frames or max(args.delay) >= frames:
        raise ValueError(f"--onset and every --delay must be below the {frames} frames")
    text, record = "", {}
    for k, (name, require) in enumerate(SETS.items()):
        start = design(ckpt, require, out / f"set{k}" / "design", args)
        found = stream(ckpt, require, start, out / f"set{k}", frames, args, onset)
        text += table(name, start, found, onset, frames) + "\n"
        record[name] = {
            "requirements": require, "certified_start": start is not None,
            "runs": {s: {f"eta {e:g}, delay {d}": v for (e, d), v in r.items()}
                     for s, r in found.items()},
        }  # fmt: skip
    (out / "study.md").write_text(text)
    (out / "study.json").write_text(json.dumps(record, indent=2))
    print(text)


if __name__ == "__main__":
    with user_errors(subprocess.CalledProcessError):
        main()
