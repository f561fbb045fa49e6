"""`evaluate.py` under torchrun with 2 CPU processes (gloo) gives the single-process numbers."""

import json
import math
import subprocess
import sys
from pathlib import Path

from costseg.checkpoints import find_checkpoint

ROOT = Path(__file__).resolve().parents[1]


def _evaluate(launcher: list[str], ckpt: Path, out: Path) -> dict:
    args = ["--ckpt_path", str(ckpt), "--output_dir", str(out), "--no-progress"]
    args += ["--cost", "robotistic", "egoistic", "ml", "--num_examples", "0", "--batch_size", "1"]
    done = subprocess.run(
        [*launcher, str(ROOT / "evaluate.py"), *args], capture_output=True, text=True, timeout=600
    )
    assert done.returncode == 0, done.stderr[-3000:]
    return json.loads((out / "results.json").read_text())


def test_two_processes_equal_one(tiny_run, tmp_path):
    ckpt = find_checkpoint(None, runs_dir=tiny_run[2])
    single = _evaluate([sys.executable], ckpt, tmp_path / "one")
    torchrun = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node=2"]
    double = _evaluate(torchrun, ckpt, tmp_path / "two")
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
