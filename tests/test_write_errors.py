"""Failures that are and are not the user's: a full disk under TensorBoard's writer thread is one
line naming the folder (exit 2); a missing optional extra is one line naming the extra; a broken
import of costseg's own code is a traceback, not a user mistake."""

import subprocess
import sys

import pytest

from costseg.checkpoints import find_checkpoint
from costseg.cli import evaluate_main, train_main

# evaluate.py with TensorBoard's record writer failing, as on a full disk, from its second record
# on: the failure happens in the writer's thread (the first record is the file header).
FULL_DISK = """
import errno, os, sys
from tensorboard.summary.writer.record_writer import RecordWriter
write, calls = RecordWriter.write, []
def full(self, data):
    calls.append(data)
    if len(calls) > 1:
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
    write(self, data)
RecordWriter.write = full
from costseg.cli import evaluate_main
evaluate_main(sys.argv[1:])
"""


@pytest.fixture(scope="module")
def ckpt(tiny_run):
    return str(find_checkpoint(None, runs_dir=tiny_run[2]))


def test_a_full_disk_under_the_tensorboard_thread_is_one_line_naming_the_folder(ckpt, tmp_path):
    out = tmp_path / "out"
    args = ["--ckpt_path", ckpt, "--cost", "robotistic", "--limit", "1", "--num_examples", "0"]
    done = subprocess.run(
        [sys.executable, "-c", FULL_DISK, *args, "--output_dir", str(out), "--no-progress"],
        capture_output=True,
        text=True,
    )
    lines = done.stderr.strip().splitlines()
    assert done.returncode == 2, done.stderr
    assert len(lines) == 1, done.stderr  # no traceback from the writer thread
    assert lines[0].startswith("error: No space left on device: "), lines
    assert f"{out};" in lines[0], lines


def test_a_missing_extra_is_one_line_naming_it(tmp_path, monkeypatch, capsys):
    import costseg.evaluation.run  # noqa: F401  (before: torchmetrics tries transformers too)

    monkeypatch.setitem(sys.modules, "transformers", None)  # as if the extra were not installed
    (tmp_path / "model").mkdir()
    with pytest.raises(SystemExit) as exit_info:
        evaluate_main(["--network", f"hf:{tmp_path / 'model'}", "--no-progress"])
    assert exit_info.value.code == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert lines == ["error: hf: networks need transformers: pip install 'costseg[hf]'"]


def test_a_broken_import_of_costseg_is_not_a_user_mistake(monkeypatch):
    monkeypatch.setitem(sys.modules, "costseg.training.run", None)  # import fails
    with pytest.raises(ImportError, match=r"costseg\.training\.run"):
        train_main(["--trainer.max_steps=1"])


def test_a_full_disk_during_training_is_one_line_naming_the_run(tmp_path, monkeypatch, capsys):
    from conftest import TINY_TRAIN

    from costseg.training.logger import RunLogger

    def full(self, metrics, step=None):
        raise OSError(28, "No space left on device")  # as TensorBoard raises it: no file name

    monkeypatch.setattr(RunLogger, "log_metrics", full)
    with pytest.raises(SystemExit) as exit_info:
        train_main([*TINY_TRAIN, f"--trainer.logger.init_args.save_dir={tmp_path}"])
    assert exit_info.value.code == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: [Errno 28] No space left on device: ")
    assert str(tmp_path / "toy" / "version_0") in lines[0]
