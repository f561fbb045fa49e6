"""`evaluate.py` under torchrun with 2 CPU processes (gloo) gives the single-process numbers."""

import json
import math
import subprocess
import sys
from pathlib import Path

from costseg.checkpoints import find_checkpoint
from costseg.cli import evaluate_main

ROOT = Path(__file__).resolve().parents[1]


def _arguments(ckpt: Path, out: Path) -> list[str]:
    costs = ["--cost", "robotistic", "egoistic", "ml"]
    rest = ["--num_examples", "0", "--batch_size", "1", "--no-progress"]
    return ["--ckpt_path", str(ckpt), "--output_dir", str(out), *costs, *rest]


def test_two_processes_equal_one(tiny_run, tmp_path):
    ckpt = find_checkpoint(None, runs_dir=tiny_run[2])
    evaluate_main(_arguments(ckpt, tmp_path / "one"))  # the single process: this one
    single = json.loads((tmp_path / "one" / "results.json").read_text())
    torchrun = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node=2"]
    command = [*torchrun, str(ROOT / "evaluate.py"), *_arguments(ckpt, tmp_path / "two")]
    done = subprocess.run(command, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    double = json.loads((tmp_path / "two" / "results.json").read_text())
    assert single["rows"] == double["rows"]
    assert single["confusion_matrix"] == double["confusion_matrix"]
    assert single["miou"] == double["miou"]


def test_validation_metrics_with_two_ddp_processes_equal_one(tiny_run):
    import lightning as L

    from costseg.data.datamodule import StreetScenesDataModule

    module = tiny_run[0]
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
