"""`evaluate.py` under torchrun with 2 CPU processes (gloo) gives the single-process outputs:
every analysis of the table, every results.json field, CSV and figure."""

import csv
import json
import math
import subprocess
import sys
from pathlib import Path

import pytest
from conftest import EVERY_OUTPUT, every_output_arguments

from costseg.checkpoints import find_checkpoint
from costseg.cli import evaluate_parser
from costseg.evaluation.analyses import ANALYSES, wanted
from costseg.options import EvalOptions

pytestmark = pytest.mark.e2e  # torchrun with two processes against one

ROOT = Path(__file__).resolve().parents[1]

VARYING = {"output_dir", "source", "timing"}
"""results.json keys that name the run's own folder or time."""


def test_the_evaluation_runs_every_analysis():
    opts = EvalOptions(**vars(evaluate_parser().parse_args(EVERY_OUTPUT[0])))
    assert {e.module for e, _ in wanted(opts)} == {e.module for e in ANALYSES}


def test_two_processes_equal_one(every_output, tiny_run, tmp_path):
    """The session's evaluation of every analysis (one process, one thread, as torchrun runs
    each process) against the same under torchrun."""
    ckpt = find_checkpoint(None, runs_dir=tiny_run.runs)
    one, two = every_output[0], tmp_path / "two"
    torchrun = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node=2"]
    command = [*torchrun, str(ROOT / "evaluate.py"), *every_output_arguments(ckpt, two, 0)]
    done = subprocess.run(command, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    single, double = (json.loads((d / "results.json").read_text()) for d in (one, two))
    assert single.keys() == double.keys()
    for results in (single, double):
        del results["options"]["output_dir"]
    for key in single.keys() - VARYING:
        _assert_equal(single[key], double[key], key)
    files = [sorted(p.relative_to(d) for p in d.rglob("*") if p.is_file() and "events" not in
                    p.name and p.suffix != ".html") for d in (one, two)]  # fmt: skip
    assert files[0] == files[1]
    for path in files[0]:
        if path.suffix == ".csv":
            _assert_equal(_cells(one / path), _cells(two / path), str(path))
        elif path.suffix in (".md", ".yaml"):
            assert (one / path).read_text() == (two / path).read_text(), path


def _cells(path: Path) -> list[list]:
    """A CSV file's cells, numbers as floats."""
    with path.open() as f:
        return [[_number(cell) for cell in row] for row in csv.reader(f)]


def _number(cell: str):
    try:
        return float(cell)
    except ValueError:
        return cell


def _assert_equal(a, b, where: str) -> None:
    """Equal values, floats to float32 rounding (sums over processes), NaN equal to NaN."""
    if isinstance(a, dict):
        assert a.keys() == b.keys(), where
        for k in a:
            _assert_equal(a[k], b[k], f"{where}.{k}")
    elif isinstance(a, list):
        assert len(a) == len(b), where
        for i, (x, y) in enumerate(zip(a, b, strict=True)):
            _assert_equal(x, y, f"{where}[{i}]")
    elif isinstance(a, float) and isinstance(b, float):
        assert math.isclose(a, b, rel_tol=1e-5, abs_tol=1e-9) or (
            math.isnan(a) and math.isnan(b)
        ), where
    else:
        assert a == b, where


def test_validation_metrics_with_two_ddp_processes_equal_one(tiny_run):
    import lightning as L

    from costseg.data.datamodule import StreetScenesDataModule

    module = tiny_run.module
    data = StreetScenesDataModule(
        batch_size=1, num_workers=0, size=(64, 128), train_length=8, val_length=4
    )
    results = []
    for devices, strategy in ((1, "auto"), (2, "ddp_spawn")):
        trainer = L.Trainer(
            accelerator="cpu",
            devices=devices,
            strategy=strategy,
            logger=False,
            enable_progress_bar=False,
            enable_model_summary=False,
        )
        results.append(trainer.validate(module, data, verbose=False)[0])
    assert results[0].keys() == results[1].keys()
    for key, value in results[0].items():
        if key != "val/loss":  # a mean of per-process means, not a sum of counts
            assert value == results[1][key] or (math.isnan(value) and math.isnan(results[1][key]))
