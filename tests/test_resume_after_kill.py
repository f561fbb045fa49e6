"""A real `train.py` killed with SIGKILL resumes from the periodic last.ckpt without loss (the
resumed run in the test process, with the same arguments)."""

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch
import yaml
from conftest import TINY_TRAIN
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

from costseg import CONFIGS
from costseg.cli import train_main

pytestmark = pytest.mark.e2e  # a training killed and resumed

ROOT = Path(__file__).resolve().parents[1]
EVERY = 2


def _config(tmp_path: Path) -> Path:
    """The packaged toy.yaml with the periodic last.ckpt every EVERY steps."""
    config = yaml.safe_load((CONFIGS / "toy.yaml").read_text())
    periodic = [
        c for c in config["trainer"]["callbacks"] if "every_n_train_steps" in c["init_args"]
    ]
    assert len(periodic) == 1  # the shipped config saves last.ckpt periodically
    periodic[0]["init_args"]["every_n_train_steps"] = EVERY
    path = tmp_path / "toy.yaml"
    path.write_text(yaml.safe_dump(config))
    return path


def _arguments(config: Path, *extra: str) -> list[str]:
    args = [a for a in TINY_TRAIN if not a.startswith(("--trainer.max_steps", "--trainer.val"))]
    args += ["--trainer.log_every_n_steps=1", "--trainer.val_check_interval=1000", *extra]
    return [f"--config={config}", *args]


def _saved_step(path: Path) -> int | None:
    try:
        return torch.load(path, map_location="cpu", weights_only=True)["global_step"]
    except Exception:  # not written yet, or being replaced
        return None


def test_killed_training_resumes_with_step_optimizer_and_schedule(tmp_path, monkeypatch, capsys):
    config = _config(tmp_path)
    last = tmp_path / "runs" / "toy" / "version_0" / "checkpoints" / "last.ckpt"
    arguments = _arguments(config, "--trainer.max_steps=100000")
    command = [sys.executable, str(ROOT / "train.py"), *arguments]
    job = subprocess.Popen(command, cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    deadline = time.monotonic() + 300
    while (_saved_step(last) or 0) < EVERY:
        assert job.poll() is None and time.monotonic() < deadline, job.stdout.read().decode()
        time.sleep(0.2)
    os.kill(job.pid, signal.SIGKILL)
    job.wait()
    saved = _saved_step(last)
    assert saved is not None and saved % EVERY == 0
    monkeypatch.chdir(tmp_path)  # as the killed run: runs/ and the priors cache beside it
    train_main(_arguments(config, f"--trainer.max_steps={saved + 2}", "--ckpt_path=last"))
    output = capsys.readouterr().out
    assert f"resuming from {Path('runs/toy/version_0/checkpoints/last.ckpt')}" in output
    # The resumed run trained only the 2 missing steps, logged at the continued step numbers...
    events = EventAccumulator(str(tmp_path / "runs" / "toy" / "version_1"))
    events.Reload()
    steps = [e.step for e in events.Scalars("train/loss")]
    assert steps == [saved, saved + 1]
    # ...and its optimizer and schedule continued from the killed run's state.
    final = torch.load(
        tmp_path / "runs" / "toy" / "version_1" / "checkpoints" / "last.ckpt",
        map_location="cpu",
        weights_only=True,
    )
    assert final["global_step"] == saved + 2
    adam_steps = {float(s["step"]) for s in final["optimizer_states"][0]["state"].values()}
    assert adam_steps == {saved + 2.0}
    assert final["lr_schedulers"][0]["last_epoch"] == saved + 2
