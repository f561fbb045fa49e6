"""A newcomer's mistakes with `python train.py`: each ends in one line `error: ...` naming the
option to change, exit status 2, before the priors are counted and before the first step."""

import shutil

import pytest
import torch
from conftest import TINY_TRAIN

from costseg.cli import CLASS_PREFIX, train_main

ADAPTER = "costseg.models.adapter.NetworkAdapter"
DICT_LOGITS = ["--model.net=" + ADAPTER, "--model.net.init_args.builder=own_networks.DictLogits"]
TINY = [a for a in TINY_TRAIN if not a.startswith("--model.net")]  # those are DeepLabV3Plus's
CITYSCAPES_ON_CPU = [
    "--config=cityscapes",
    "--trainer.accelerator=cpu",
    "--trainer.precision=32-true",
    "--model.net.init_args.backbone=resnet18",
    "--model.net.init_args.decoder_channels=16",
    "--data.init_args.num_workers=0",
]

MISTAKES = {
    "class count": (
        [*TINY_TRAIN, "--model.num_classes=7"],
        ["--model.num_classes is 7", "has 19 classes", "pass --model.num_classes 19"],
    ),
    "adapter given another num_classes": (
        [*TINY, *DICT_LOGITS, "--model.net.init_args.builder_args={num_classes: 21}"],
        ["--model.net.init_args.builder_args holds num_classes: 21", "model.num_classes = 19"],
    ),
    "adapter's output key": (
        [*TINY, *DICT_LOGITS, "--model.net.init_args.output=logits"],
        ["keys ['out'], without 'logits'", "set --model.net.init_args.output"],
    ),
    "weights in 16 bits": (
        [*TINY_TRAIN, "--trainer.precision=16-true"],
        ["--trainer.precision 16-true keeps the weights in 16 bits", "32-true"],
    ),
    "bf16 weights": ([*TINY_TRAIN, "--trainer.precision=bf16-true"], ["bf16-true", "32-true"]),
    "float16 autocast on a CPU": (
        [*TINY_TRAIN, "--trainer.accelerator=cpu", "--trainer.precision=16-mixed"],
        ["--trainer.precision 16-mixed is not available", "(cpu;", "bf16-mixed or 32-true"],
    ),
}


def _refused(args, capsys, monkeypatch, *needles):
    """train_main(args) ends in one line holding ``needles``, exit 2, the priors never counted."""

    def reached(*_, **__):
        raise AssertionError("the priors were reached before the mistake was refused")

    monkeypatch.setattr("costseg.data.priors_cache.training_priors", reached)
    with pytest.raises(SystemExit) as exit_info:
        train_main(args)
    assert exit_info.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    assert err[0].startswith("error: ") and not CLASS_PREFIX.match(err[0][7:]), err[0]
    assert all(n in err[0] for n in needles), err[0]
    return err[0]


@pytest.mark.parametrize("case", sorted(MISTAKES))
def test_a_mistake_is_one_line_before_the_priors(case, tmp_path, capsys, monkeypatch):
    args, needles = MISTAKES[case]
    logs = f"--trainer.logger.init_args.save_dir={tmp_path}"
    _refused([*args, logs], capsys, monkeypatch, *needles)
    assert not any(tmp_path.iterdir())  # no run folder, no cache


def test_a_missing_cityscapes_root_names_the_option(tmp_path, capsys, monkeypatch):
    root = tmp_path / "nowhere"
    args = [*CITYSCAPES_ON_CPU, f"--data.init_args.root={root}"]
    logs = f"--trainer.logger.init_args.save_dir={tmp_path / 'runs'}"
    needle = f"--data.init_args.root: Cityscapes root '{root}' does not exist"
    _refused([*args, logs], capsys, monkeypatch, needle)
    assert not (tmp_path / "runs").exists()


def test_a_cityscapes_root_without_its_training_labels_names_the_folder(
    cityscapes_root, tmp_path, capsys, monkeypatch
):
    shutil.rmtree(cityscapes_root / "gtFine" / "train")
    args = [*CITYSCAPES_ON_CPU, f"--data.init_args.root={cityscapes_root}"]
    missing = cityscapes_root / "gtFine" / "train"
    logs = f"--trainer.logger.init_args.save_dir={tmp_path / 'runs'}"
    needles = ["--data.init_args.root: ", f"'{missing}' does not exist"]
    line = _refused([*args, logs], capsys, monkeypatch, *needles)
    assert "Errno" not in line and not (tmp_path / "runs").exists()


def test_an_adapter_given_the_same_num_classes_takes_it_once():
    """torchvision users pass num_classes by habit: the same count is taken once (and not
    recorded twice, so a checkpoint rebuilds the network)."""
    from costseg.models.adapter import NetworkAdapter

    net = NetworkAdapter("own_networks.DictLogits", 5, {"num_classes": 5})
    assert net.init_args["builder_args"] == {} and net.init_args["num_classes"] == 5
    assert net(torch.zeros(1, 3, 8, 8)).shape == (1, 5, 2, 2)
