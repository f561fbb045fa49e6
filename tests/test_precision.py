"""The training precision: chosen by the machine when unset, the user's when set."""

import pytest
import torch
from conftest import TINY_TRAIN

from costseg.cli import train_main
from costseg.training import precision

pytestmark = pytest.mark.e2e  # trainings at each precision

UNSET = [a for a in TINY_TRAIN if not a.startswith("--trainer.precision")]


# The machine, as torch's probes report it, and the expected choice: (accelerator, AVX512-BF16,
# AMX, CUDA available, CUDA bf16) → (precision, the device its reason names).
MACHINES = [
    ("cpu", False, False, False, False, "32-true", "CPU"),
    ("cpu", True, False, False, False, "bf16-mixed", "CPU"),
    ("cpu", False, True, False, False, "bf16-mixed", "CPU"),
    ("cpu", False, False, True, True, "32-true", "CPU"),  # a GPU the run does not use
    ("auto", True, True, False, False, "bf16-mixed", "CPU"),
    ("auto", False, False, False, True, "32-true", "CPU"),
    ("auto", True, True, True, False, "32-true", "GPU"),  # auto trains on the GPU
    ("auto", False, False, True, True, "bf16-mixed", "GPU"),
    ("gpu", False, False, True, True, "bf16-mixed", "GPU"),
    ("cuda", True, True, True, False, "32-true", "GPU"),
    ("gpu", True, True, False, True, "32-true", "GPU"),  # no CUDA: its bf16 answer is moot
    ("mps", True, True, True, True, "32-true", "mps"),
]


@pytest.mark.parametrize(
    ("accelerator", "avx512_bf16", "amx", "cuda", "cuda_bf16", "expected", "device"), MACHINES
)
def test_choice_follows_the_hardware_probes(
    monkeypatch, accelerator, avx512_bf16, amx, cuda, cuda_bf16, expected, device
):
    monkeypatch.setattr(torch.cpu, "_is_avx512_bf16_supported", lambda: avx512_bf16, raising=False)
    monkeypatch.setattr(torch.cpu, "_is_amx_tile_supported", lambda: amx, raising=False)
    monkeypatch.setattr(torch.cuda, "is_available", lambda: cuda)
    monkeypatch.setattr(torch.cuda, "is_bf16_supported", lambda *args, **kwargs: cuda_bf16)
    chosen, why = precision.choose_precision(accelerator)
    assert chosen == expected
    assert device in why
    assert ("natively" in why) == (expected == "bf16-mixed")


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
