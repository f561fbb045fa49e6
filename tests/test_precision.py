"""The training precision: chosen by the machine when unset, the user's when set."""

import pytest
from conftest import TINY_TRAIN

from costseg.cli import train_main
from costseg.training import precision

UNSET = [a for a in TINY_TRAIN if not a.startswith("--trainer.precision")]


@pytest.mark.parametrize("native", [True, False])
def test_cpu_choice_follows_native_bf16(monkeypatch, native):
    monkeypatch.setattr(precision, "cpu_has_native_bf16", lambda: native)
    chosen, why = precision.choose_precision("cpu")
    assert chosen == ("bf16-mixed" if native else "32-true")
    assert ("natively" in why) == native


def test_gpu_choice_follows_native_bf16(monkeypatch):
    monkeypatch.setattr(precision, "cuda_has_native_bf16", lambda: True)
    assert precision.choose_precision("gpu")[0] == "bf16-mixed"
    monkeypatch.setattr(precision, "cuda_has_native_bf16", lambda: False)
    assert precision.choose_precision("cuda")[0] == "32-true"


@pytest.mark.parametrize(
    ("native", "given", "expected"),
    [
        (False, None, "32-true"),
        (True, None, "bf16-mixed"),
        (True, "32-true", "32-true"),  # an explicit precision always wins
        (False, "bf16-mixed", "bf16-mixed"),
    ],
)
def test_train_py_uses_the_choice_unless_told(
    monkeypatch, tmp_path, capsys, native, given, expected
):
    monkeypatch.setattr(precision, "cpu_has_native_bf16", lambda: native)
    args = [*UNSET, "--trainer.accelerator=cpu", "--trainer.fast_dev_run=true"]
    if given is not None:
        args.append(f"--trainer.precision={given}")
    save = [
        f"--trainer.default_root_dir={tmp_path}",
        f"--trainer.logger.init_args.save_dir={tmp_path}",
    ]
    _, trainer = train_main([*args, *save])
    assert trainer.precision == expected
    lines = [line for line in capsys.readouterr().out.splitlines() if line.startswith("precision")]
    assert lines == [lines[0]] and lines[0].startswith(f"precision: {expected} (")
