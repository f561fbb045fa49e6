"""The command lines' rough edges: options declared once, TensorBoard cards, Ctrl-C, a full disk,
runs that fail before training, one last.ckpt, progress in a log file."""

import dataclasses
import errno
import io
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from conftest import TINY_TRAIN
from interrupts import ENV, ROOT, interrupt_when, start_job
from lightning.pytorch import LightningModule, Trainer  # imported at collection (log handler)
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

from costseg.checkpoints import find_checkpoint
from costseg.cli import evaluate_main, evaluate_parser, train_main
from costseg.options import EvalOptions
from costseg.progress import Progress
from costseg.report.outputs import INCOMPLETE

pytestmark = pytest.mark.e2e  # commands interrupted in subprocesses


@pytest.fixture(scope="module")
def ckpt(tiny_run):
    return str(find_checkpoint(None, runs_dir=tiny_run[2]))


def _scalar_tags(folder: Path) -> dict[str, int]:
    """Scalar tag → points, over every event file under ``folder`` (a card per tag)."""
    tags: dict[str, int] = {}
    for run in {p.parent for p in folder.rglob("events.out.tfevents.*")}:
        events = EventAccumulator(str(run), size_guidance={"scalars": 0})
        events.Reload()
        for tag in events.Tags()["scalars"]:
            tags[tag] = tags.get(tag, 0) + len(events.Scalars(tag))
    return tags


def test_every_option_is_declared_once_and_shown_in_help():
    parser = evaluate_parser()
    assert vars(parser.parse_args([])) == dataclasses.asdict(EvalOptions())
    text = parser.format_help()
    for field in dataclasses.fields(EvalOptions):
        flag = field.metadata.get("flag", f"--{field.name}")
        assert flag in text and field.metadata["help"], field.name
    command = "import sys; from costseg.cli import evaluate_parser; evaluate_parser().format_help()"
    command += "; print(sorted({'torch', 'lightning'} & set(sys.modules)))"
    out = subprocess.run([sys.executable, "-c", command], env=ENV, capture_output=True, text=True)
    assert out.stdout.strip() == "[]", out.stderr  # --help imports nothing heavy


def test_one_evaluation_writes_few_scalar_cards(ckpt, tmp_path):
    out = tmp_path / "out"
    args = ["--ckpt_path", ckpt, "--cost", "robotistic", "altruistic", "egoistic", "ml"]
    args += ["--sweep", "0.5", "--alpha_sweep", "0.5", "--limit", "2", "--num_examples", "0"]
    evaluate_main([*args, "--output_dir", str(out), "--no-progress"])
    tags = _scalar_tags(out)
    assert len(tags) <= 30, sorted(tags)
    assert not {"epoch", "hp_metric"} & set(tags)
    assert tags["sweep/miou"] == 6 and tags["alpha_sweep/miou"] == 3  # curves, not points
    assert not (out / INCOMPLETE).exists()


def test_training_writes_no_constant_cards_and_one_last_checkpoint(tiny_run):
    _, trainer, _ = tiny_run
    run = Path(trainer.log_dir)
    assert not {"epoch", "hp_metric"} & set(_scalar_tags(run))
    assert sorted(p.name for p in (run / "checkpoints").glob("last*.ckpt")) == ["last.ckpt"]


def test_a_run_that_fails_before_training_leaves_no_folder(tmp_path, monkeypatch, capsys):
    from costseg.training.module import SegmentationModule

    def broken(self):
        raise ValueError("no optimiser today")

    monkeypatch.setattr(SegmentationModule, "configure_optimizers", broken)
    with pytest.raises(SystemExit) as exit_info:
        train_main([*TINY_TRAIN, f"--trainer.logger.init_args.save_dir={tmp_path}"])
    assert exit_info.value.code == 2
    assert capsys.readouterr().err.strip().splitlines()[-1] == "error: no optimiser today"
    # no run folder (the priors are cached beside the runs folder, for the next run)
    assert not any(tmp_path.iterdir()), list(tmp_path.rglob("*"))


def test_a_full_disk_is_one_line_and_the_folder_stays_incomplete(
    ckpt, tmp_path, monkeypatch, capsys
):
    import costseg.report.files as files

    write = files.write_bytes

    def full(path, data):
        if str(path).endswith(".csv"):
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(path))
        return write(path, data)

    # this process's writes; a figure worker's failed write: tests/test_drawing.py
    monkeypatch.setattr(files, "write_bytes", full)
    out = tmp_path / "out"
    args = ["--ckpt_path", ckpt, "--cost", "robotistic", "--limit", "1", "--output_dir", str(out)]
    with pytest.raises(SystemExit) as exit_info:
        evaluate_main([*args, "--no-progress"])
    assert exit_info.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "No space left on device" in err[0] and INCOMPLETE in err[0], err
    assert (out / INCOMPLETE).is_file()


def test_ctrl_c_during_evaluation(ckpt, tmp_path):
    out = tmp_path / "out"
    command = [sys.executable, str(ROOT / "evaluate.py"), "--ckpt_path", ckpt, "--no-progress"]
    command += ["--sweep", "0.05", "--output_dir", str(out)]
    job = start_job(command)
    output, err = interrupt_when(job, (out / "figures").exists)  # drawing while scoring
    assert job.returncode == 130, (output, err)
    assert err.strip().splitlines() == [
        f"interrupted: the partial outputs in {out} are marked {INCOMPLETE}"
    ]
    assert (out / INCOMPLETE).is_file()  # whatever was written before the interrupt
    # A later run does not take the unfinished folder for results, nor overwrite it silently.
    with pytest.raises(SystemExit):
        evaluate_main(["--ckpt_path", ckpt, "--output_dir", str(out), "--no-progress"])


def test_ctrl_c_during_training(tmp_path):
    run = tmp_path / "toy" / "version_0"
    command = [sys.executable, str(ROOT / "train.py"), *TINY_TRAIN, "--trainer.max_steps=100000"]
    command += [f"--trainer.logger.init_args.save_dir={tmp_path}"]
    job = start_job(command)
    output, err = interrupt_when(job, lambda: any(run.glob("events.out.tfevents.*")))
    assert job.returncode == 130, (output, err)
    assert "Traceback" not in err and "KeyboardInterrupt" not in err, err
    assert err.strip().splitlines()[-1].startswith("interrupted: "), err


def test_progress_in_a_log_file_is_a_line_every_five_percent():
    log = io.StringIO()  # not a terminal
    with Progress(1000, "train", every=5, file=log) as bar:
        for step in range(1000):
            bar.update(postfix={"loss": 1 / (step + 1)})
    lines = log.getvalue().splitlines()
    assert len(lines) == 20 and lines[-1].startswith("train: 1000/1000 (100%)"), lines[:3]


def test_training_progress_counts_steps(capsys):
    """Optimiser steps (not batches, not epochs) towards max_steps: a line every 5 % in a log."""
    from costseg.training.run import _use_step_progress

    class Line(LightningModule):  # y = w x on random batches: the smallest model that trains
        def __init__(self) -> None:
            super().__init__()
            self.w = torch.nn.Linear(1, 1)

        def training_step(self, batch, batch_idx):
            return self.w(batch).square().mean()

        def train_dataloader(self):
            return torch.utils.data.DataLoader(torch.randn(64, 1), batch_size=2)

        def configure_optimizers(self):
            return torch.optim.SGD(self.parameters(), lr=0.01)

    trainer = Trainer(
        max_steps=40, accumulate_grad_batches=2, logger=False, enable_checkpointing=False,
        enable_model_summary=False,
    )  # fmt: skip
    _use_step_progress(trainer)  # in place of Lightning's bar, which counts epochs
    trainer.fit(Line())
    lines = [line for line in capsys.readouterr().err.splitlines() if line.startswith("train:")]
    assert [line.split()[1] for line in lines] == [f"{n}/40" for n in range(2, 41, 2)], lines
    assert trainer.global_step == 40  # after 80 batches in 3 epochs


def test_result_json_is_written_once_complete(ckpt, tmp_path):
    out = tmp_path / "out"
    args = ["--ckpt_path", ckpt, "--cost", "robotistic", "--limit", "1", "--num_examples", "0"]
    evaluate_main([*args, "--output_dir", str(out), "--no-progress"])
    assert json.loads((out / "results.json").read_text())["images"] == 1
    assert not (out / INCOMPLETE).exists()
