"""``make demo``: train the default model, evaluate it under the paper's rules, time both halves.

    python scripts/demo.py [--runs runs]

Runs ``train.py`` and then ``evaluate.py --cost robotistic altruistic egoistic ml --sweep 0.1`` on
the checkpoint it wrote, each in its own process with its output shown as it comes, and ends with
the wall time of both and the folder of results. A failing step ends the demo with its status.
"""

from __future__ import annotations

import subprocess
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from costseg.cli import parse_options
from costseg.options import option

EVALUATE = ["--cost", "robotistic", "altruistic", "egoistic", "ml", "--sweep", "0.1"]


@dataclass
class DemoOptions:
    """What ``demo.py`` can be told (``--help``)."""

    runs: Path = option(Path("runs"), "the runs folder (train.py's save_dir)", type=Path)


def _run(args: list[str]) -> float:
    """Run ``python ARGS`` in the repository root; its wall time in seconds (exit on failure)."""
    start = time.perf_counter()
    status = subprocess.call([sys.executable, *args], cwd=Path(__file__).resolve().parents[1])
    if status != 0:
        sys.exit(status)
    return time.perf_counter() - start


def _minutes(seconds: float) -> str:
    return f"{int(seconds // 60)}:{seconds % 60:04.1f}"


def _newest(pattern: str, runs: Path) -> Path:
    return max(runs.glob(pattern), key=lambda p: p.stat().st_mtime)


def main(args: Sequence[str] | None = None) -> None:
    runs = parse_options(DemoOptions, args, "demo.py", __doc__.splitlines()[0]).runs
    try:
        train = _run(["train.py", f"--trainer.logger.init_args.save_dir={runs}"])
        checkpoint = _newest("*/version_*/checkpoints/last.ckpt", runs)
        evaluate = _run(["evaluate.py", "--ckpt_path", str(checkpoint), *EVALUATE])
    except KeyboardInterrupt:
        print("demo interrupted", file=sys.stderr)
        sys.exit(130)
    results = _newest("*/version_*/evaluation/version_*/results.json", runs).parent
    print(
        f"demo: training {_minutes(train)}, evaluation {_minutes(evaluate)}, "
        f"in all {_minutes(train + evaluate)} (min:s)\n"
        f"results: {results}\n"
        f"everything logged: tensorboard --logdir {runs}"
    )


if __name__ == "__main__":
    main()
