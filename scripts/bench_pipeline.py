"""Speed of the evaluation pipeline, as ratios measured side by side in one run.

    python scripts/bench_pipeline.py [--ckpt_path PATH] [--sections ...] [--images 3]

Needs a trained checkpoint (default: the newest runs/**/last.ckpt, e.g. after `make demo`).
Sections:

1. start-up: `evaluate.py --help`, `train.py --help`, `import costseg.evaluation.run`, the
   imports no evaluation avoids (torch, torchvision, torchmetrics), and
   `evaluate.py` from start to its first image (when its progress bar counts the first of two
   images), each as a fresh process;
2. the 231-point sweep (step 0.05) ÷ a single-rule evaluation on the toy validation set,
   network included (the time until the outputs are written);
3. figures: the share of an evaluation of 20 toy images spent writing tables and figures;
4. full-resolution: section 2 on ``--images`` stand-in scenes written at 1024 × 2048 by
   scripts/toy_as_cityscapes.py, and the sweep's seconds per image.
"""

from __future__ import annotations

import re
import subprocess
import sys
import tempfile
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Literal, get_args

import torch

import costseg.report.evaluation as report
from costseg.checkpoints import find_checkpoint
from costseg.cli import parse_options, user_errors
from costseg.evaluation.run import evaluate
from costseg.options import EvalOptions, option
from costseg.report.evaluation import write_evaluation
from costseg.values import whole_number

ROOT = Path(__file__).resolve().parents[1]
Section = Literal["startup", "sweep", "figures", "full-resolution"]
SECTIONS = list(get_args(Section))


@dataclass
class PipelineBenchOptions:
    """What ``bench_pipeline.py`` can be told (``--help``)."""

    ckpt_path: str | None = option(
        help="a train.py checkpoint (default: the newest runs/**/last.ckpt)", metavar="PATH"
    )
    sections: list[Section] = option(SECTIONS, "the sections timed")
    images: int = option(3, "full-resolution stand-in images", type=whole_number(1))


def process_seconds(args: list[str], repeats: int = 3) -> float:
    """Best wall time of a fresh Python process running ``args``."""
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        subprocess.run([sys.executable, *args], cwd=ROOT, check=True, capture_output=True)
        times.append(time.perf_counter() - start)
    return min(times)


def first_image_seconds(args: list[str], repeats: int = 3) -> float:
    """Best wall time from the start of a fresh ``evaluate.py`` process until its progress bar
    (tqdm, on stderr) shows the first of two images done."""
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        proc = subprocess.Popen(
            [sys.executable, *args], cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE
        )
        seen = b""
        while chunk := proc.stderr.read1(4096):
            seen += chunk
            if re.search(rb"\b1/2\b", seen):
                times.append(time.perf_counter() - start)
                break
        seen += proc.stderr.read()
        if proc.wait() != 0 or len(times) == 0:
            sys.exit(f"error: {' '.join(args)} failed or showed no progress:\n{seen.decode()}")
    return min(times)


def bench_startup(ckpt: str, out: Path) -> None:
    t_eval_help = process_seconds(["evaluate.py", "--help"])
    t_train_help = process_seconds(["train.py", "--help"])
    t_import = process_seconds(["-c", "import costseg.evaluation.run"])
    t_floor = process_seconds(["-c", "import torch, torchvision, torchmetrics"])
    two = ["evaluate.py", "--ckpt_path", ckpt, "--cost", "robotistic", "--limit", "2"]
    two += ["--batch_size", "1", "--num_examples", "0", "--overwrite", "--output_dir", str(out)]
    t_first = first_image_seconds(two)
    print("start-up (fresh processes, best of 3):")
    print(f"  evaluate.py --help                       {t_eval_help:6.2f} s   (target <= 1)")
    print(f"  train.py --help                          {t_train_help:6.2f} s   (target <= 1)")
    print(f"  import costseg.evaluation.run                {t_import:6.2f} s")
    print(f"  import torch, torchvision, torchmetrics       {t_floor:6.2f} s   (before any image)")
    print(f"  evaluate.py from start to its first image {t_first:5.2f} s   (target <= 3)")


def evaluation_seconds(opts: EvalOptions) -> tuple[float, float]:
    """(seconds until the outputs are written, seconds writing them) of ``evaluate(opts)``.

    The first includes the loop over the images, and the drawing that overlaps it."""
    writing = []

    def timed(*args):
        start = time.perf_counter()
        write_evaluation(*args)
        writing.append(time.perf_counter() - start)

    report.write_evaluation = timed  # evaluate() imports it when it is called
    try:
        start = time.perf_counter()
        evaluate(opts)
        total = time.perf_counter() - start
    finally:
        report.write_evaluation = write_evaluation
    return total - writing[0], writing[0]


def bench_sweep(name: str, out: Path, images: int | None = None, **options) -> None:
    common = {"num_examples": 0, "progress": False, "overwrite": True, **options}
    single = EvalOptions(cost=["robotistic"], output_dir=str(out / "single"), **common)
    sweep = EvalOptions(cost=["robotistic"], sweep=0.05, output_dir=str(out / "sweep"), **common)
    evaluation_seconds(single)  # warm-up: caches, thread pools
    t_single = evaluation_seconds(single)[0]
    t_sweep = evaluation_seconds(sweep)[0]
    print(f"value-space sweep, {name} (network included, writing the outputs not timed):")
    print(f"  single rule {t_single:7.1f} s   231-point sweep {t_sweep:7.1f} s")
    print(f"  sweep / single rule            {t_sweep / t_single:8.2f}   (target <= 5)")
    if images:
        print(f"  sweep per image                {t_sweep / images:8.2f} s   (GPU: target <= 1 s)")


def bench_full_resolution(ckpt: str, out: Path, images: int) -> None:
    tree = out / "standin"
    script = [str(ROOT / "scripts" / "toy_as_cityscapes.py"), str(tree)]
    subprocess.run([sys.executable, *script, "--train", "1", "--val", str(images)], check=True)
    bench_sweep(f"{images} stand-in images of 1024 x 2048", out, images, ckpt_path=ckpt,
                data_root=str(tree))  # fmt: skip


def bench_figures(ckpt: str, out: Path) -> None:
    for extra in ({}, {"sweep": 0.1}):
        opts = EvalOptions(ckpt_path=ckpt, limit=20, progress=False, overwrite=True,
                           output_dir=str(out / "figures"), **extra)  # fmt: skip
        t_loop, t_write = evaluation_seconds(opts)
        share = t_write / (t_loop + t_write)
        label = "default rules" + (" + --sweep 0.1" if extra else "")
        print(
            f"figures and files, 20 toy images, {label}: loop {t_loop:.1f} s, writing "
            f"{t_write:.1f} s = {100 * share:.0f} % of the wall time (target <= 25 %)"
        )


def main(args: Sequence[str] | None = None) -> None:
    args = parse_options(PipelineBenchOptions, args, "bench_pipeline.py", __doc__.splitlines()[0])
    with user_errors():
        ckpt = str(find_checkpoint(args.ckpt_path))
    print(f"checkpoint {ckpt}; {torch.get_num_threads()} threads")
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp)
        if "startup" in args.sections:
            bench_startup(ckpt, out / "one")
        if "sweep" in args.sections:
            bench_sweep("toy validation set (100 images)", out, ckpt_path=ckpt)
        if "figures" in args.sections:
            bench_figures(ckpt, out)
        if "full-resolution" in args.sections:
            bench_full_resolution(ckpt, out, args.images)


if __name__ == "__main__":
    main()
