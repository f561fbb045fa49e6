"""A network of one's own in `train.py`: torchvision's builders through the adapter, dict
outputs, logits smaller than the input, and the one-line refusal of a network that does not fit.
"""

import re
import shlex
import textwrap
from pathlib import Path

import pytest
import torch
import yaml
from conftest import TINY_TRAIN
from own_networks import DictLogits
from torch.nn import functional as F
from torchvision.models.segmentation import deeplabv3_mobilenet_v3_large

from costseg.checkpoints import find_checkpoint
from costseg.cli import train_main
from costseg.models.adapter import NetworkAdapter
from costseg.models.entries import network_from_entry
from costseg.networks.base import IMAGENET_MEAN, IMAGENET_STD
from costseg.networks.costseg import load_costseg_checkpoint

pytestmark = pytest.mark.e2e  # trainings of other networks

ADAPTER = "costseg.models.adapter.NetworkAdapter"
MOBILENET = "torchvision.models.segmentation.deeplabv3_mobilenet_v3_large"
NO_WEIGHTS = "{weights: null, weights_backbone: null}"  # random weights: nothing downloaded
DICT_LOGITS_ARGS = [
    f"--model.net={ADAPTER}",
    "--model.net.init_args.builder=own_networks.DictLogits",
]
TINY = [a for a in TINY_TRAIN if not a.startswith("--model.net")]  # those are DeepLabV3Plus's
USAGE = (Path(__file__).resolve().parents[1] / "docs" / "usage.md").read_text()


def _documented() -> tuple[list[str], dict]:
    """The command and the YAML of docs/usage.md's "Your own network", as written there."""
    text = USAGE.split("### Your own network\n", 1)[1].split("\n### ", 1)[0]
    command, config = (textwrap.dedent(b) for b in re.findall(r"\n\n((?:    .*\n)+)", text))
    words = shlex.split(command.replace("\\\n", " "))
    assert words[:2] == ["python", "train.py"]
    return words[2:], yaml.safe_load(config)


def _train(tmp_path, *net_args):
    """2 steps of train.py with the network of ``net_args``; the module and its last.ckpt."""
    module, trainer = train_main(
        [*TINY, *net_args, f"--trainer.logger.init_args.save_dir={tmp_path}"]
    )
    assert trainer.global_step == 2
    return module.eval(), find_checkpoint(None, runs_dir=tmp_path)


def _images(b=2, h=64, w=128):
    return torch.randint(0, 256, (b, 3, h, w), dtype=torch.uint8, generator=torch.Generator())


def _normalised(images):
    mean, std = torch.tensor(IMAGENET_MEAN), torch.tensor(IMAGENET_STD)
    return (images.float() / 255 - mean.view(1, 3, 1, 1)) / std.view(1, 3, 1, 1)


def _net_state(checkpoint, prefix):
    state = torch.load(checkpoint, map_location="cpu", weights_only=True)["state_dict"]
    return {k.removeprefix(prefix): v for k, v in state.items() if k.startswith(prefix)}


def test_the_documented_command_and_config_name_torchvision_s_mobilenet_without_weights():
    args, config = _documented()
    assert args == [
        "--model.net",
        ADAPTER,
        "--model.net.init_args.builder",
        MOBILENET,
        "--model.net.init_args.builder_args",
        NO_WEIGHTS,
    ]
    entry = {"builder": MOBILENET, "builder_args": yaml.safe_load(NO_WEIGHTS)}
    assert config == {"model": {"net": {"class_path": ADAPTER, "init_args": entry}}}


def test_torchvision_deeplabv3_mobilenet_trains_and_its_checkpoint_rebuilds_it(tmp_path):
    module, last = _train(tmp_path, *_documented()[0])  # the command of docs/usage.md
    loaded = load_costseg_checkpoint(last)
    assert loaded.hparams["net"]["init_args"]["builder"] == MOBILENET
    # torchvision's own network with the checkpoint's weights is the reference
    reference = deeplabv3_mobilenet_v3_large(num_classes=19, weights=None, weights_backbone=None)
    reference.load_state_dict(_net_state(last, "net.net."))
    images = _images()
    with torch.no_grad():
        expected = reference.eval()(_normalised(images))["out"]
        torch.testing.assert_close(loaded.network(images), expected, rtol=1e-4, atol=1e-4)
        assert torch.equal(loaded.network(images), module(images))


def test_a_dict_of_smaller_logits_trains_through_the_adapter_at_the_input_size(tmp_path):
    module, last = _train(tmp_path, *DICT_LOGITS_ARGS)
    reference = DictLogits(19)
    reference.load_state_dict(_net_state(last, "net.net."))
    images = _images()
    with torch.no_grad():
        quarter = reference(_normalised(images))["out"]
        assert quarter.shape[-2:] == (16, 32)
        expected = F.interpolate(quarter, size=(64, 128), mode="bilinear", align_corners=False)
        torch.testing.assert_close(module(images), expected, rtol=1e-5, atol=1e-5)
        assert torch.equal(load_costseg_checkpoint(last).network(images), module(images))


def test_a_run_of_an_adapted_network_is_named_after_it_unless_the_command_line_names_it(tmp_path):
    one_step = [*TINY, *DICT_LOGITS_ARGS, "--trainer.max_steps=1", "--trainer.val_check_interval=1"]
    train_main([*one_step, f"--trainer.logger.init_args.save_dir={tmp_path}"])
    train_main([*one_step, f"--trainer.logger.init_args.save_dir={tmp_path}",
                "--trainer.logger.init_args.name=mine"])  # fmt: skip
    runs = sorted(p.relative_to(tmp_path).parts[0] for p in tmp_path.glob("*/version_0"))
    assert runs == ["DictLogits", "mine"]


def test_a_checkpoint_rebuilds_the_adapter_without_its_initial_weights():
    entry = {
        "class_path": ADAPTER,
        "init_args": {
            "builder": "torchvision.models.segmentation.lraspp_mobilenet_v3_large",
            "num_classes": 2,
        },
    }
    # ImageNet weights would be downloaded (given, and by default); the checkpoint's replace them
    for builder_args in ({"weights_backbone": "IMAGENET1K_V1"}, {}):
        entry["init_args"]["builder_args"] = builder_args
        net = network_from_entry(entry, initial_weights=False)
        assert net.init_args["builder_args"] == {"weights": None, "weights_backbone": None}


def test_the_adapter_names_a_missing_output_key():
    net = NetworkAdapter("own_networks.DictLogits", 3, output="logits")
    with pytest.raises(ValueError, match=r"keys \['out'\], without 'logits': set --model.net"):
        net(torch.zeros(1, 3, 8, 8))
    with pytest.raises(ValueError, match=r"not a torch\.nn\.Module class or a function returning"):
        NetworkAdapter("os.path.join", 3)


BAD_NETWORKS = {
    "builder function as class_path": (
        [f"--model.net.class_path={MOBILENET}"],
        ["model.net names a function", f"--model.net {ADAPTER}", f"builder {MOBILENET}"],
    ),
    "dict output": (
        ["--model.net=own_networks.DictLogits"],
        ["returned a dict with keys ['out']", "builder own_networks.DictLogits"],
    ),
    "wrong class count": (
        ["--model.net=own_networks.ThreeClasses"],
        ["logits of 3 classes", "model.num_classes is 19"],
    ),
    "no num_classes": (["--model.net=own_networks.NoClasses"], ["must take num_classes"]),
    "wrong output key": (
        [
            f"--model.net={ADAPTER}",
            "--model.net.init_args.builder=own_networks.DictLogits",
            "--model.net.init_args.output=logits",
        ],
        ["set --model.net.init_args.output"],
    ),
}


@pytest.mark.parametrize("case", sorted(BAD_NETWORKS))
def test_a_network_that_does_not_fit_is_refused_in_one_line_before_training(case, tmp_path, capsys):
    args, needles = BAD_NETWORKS[case]
    with pytest.raises(SystemExit) as exit_info:
        train_main([*TINY, *args, f"--trainer.logger.init_args.save_dir={tmp_path}"])
    assert exit_info.value.code == 2
    out, err = capsys.readouterr()
    err = err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: "), err
    assert all(n in err[0] for n in needles), err[0]
    assert "priors" not in out and not any(tmp_path.iterdir())  # nothing ran, nothing written
