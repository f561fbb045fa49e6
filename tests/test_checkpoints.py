"""The one checkpoint reader: weights and plain data only (a pickled object that would run code
is refused before it runs), the costseg entries under CHECKPOINT_KEY, one class check."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from costseg.checkpoints import CHECKPOINT_KEY, read_checkpoint, read_torch_file
from costseg.classes import CLASS_NAMES

RAN = []


class Payload:
    """Unpickling this would call ``RAN.append`` (what a malicious checkpoint does)."""

    def __reduce__(self):
        return (RAN.append, ("code ran",))


def _costseg(path: Path, classes, **extra) -> Path:
    weights = {"net.w": torch.ones(2)}
    torch.save({"state_dict": weights, CHECKPOINT_KEY: {"class_names": classes, **extra}}, path)
    return path


def test_code_in_a_pickle_never_runs(tmp_path: Path) -> None:
    path = _costseg(tmp_path / "evil.ckpt", list(CLASS_NAMES), trap=Payload())
    assert RAN == []
    with pytest.raises(ValueError, match="holds objects other than weights and plain data"):
        read_checkpoint(path, CLASS_NAMES)
    assert RAN == []  # weights_only=True refused the object instead of calling it


def test_plain_data_tensors_and_numpy_scalars_load(tmp_path: Path) -> None:
    path = _costseg(
        tmp_path / "ok.ckpt", list(CLASS_NAMES), priors=torch.rand(19, 2, 3), data={"a": (1, 2)}
    )
    checkpoint = read_checkpoint(path, CLASS_NAMES)
    assert checkpoint[CHECKPOINT_KEY]["data"] == {"a": (1, 2)}
    assert torch.equal(checkpoint["state_dict"]["net.w"], torch.ones(2))
    torch.save({"best_score": np.float64(0.5)}, tmp_path / "vainf.pth")
    assert read_torch_file(tmp_path / "vainf.pth") == {"best_score": 0.5}


def test_the_one_class_check(tmp_path: Path) -> None:
    path = _costseg(tmp_path / "three.ckpt", ["road", "car", "person"])
    with pytest.raises(ValueError) as caught:
        read_checkpoint(path, CLASS_NAMES)
    assert str(caught.value) == (
        f"checkpoint {path} was trained on 3 classes (road, car, person, ...), but 19 classes "
        "are expected (road, sidewalk, building, ...)"
    )
    assert read_checkpoint(path, ["road", "car", "person"])[CHECKPOINT_KEY]["class_names"] == [
        "road",
        "car",
        "person",
    ]
    torch.save({"state_dict": {}, CHECKPOINT_KEY: {}}, tmp_path / "nolist.ckpt")
    with pytest.raises(ValueError, match="no class list"):
        read_checkpoint(tmp_path / "nolist.ckpt", CLASS_NAMES)
    torch.save({"state_dict": {}}, tmp_path / "other.ckpt")
    with pytest.raises(ValueError, match="is not a costseg checkpoint"):
        read_checkpoint(tmp_path / "other.ckpt", CLASS_NAMES)


def test_a_lightning_checkpoint_of_train_py_loads_with_weights_only(tiny_run) -> None:
    """Hyper-parameters, optimiser and loop states and the costseg entries: all plain data."""
    module, _, runs = tiny_run
    checkpoint = read_checkpoint(next(runs.glob("**/last.ckpt")), CLASS_NAMES)
    assert checkpoint["hyper_parameters"]["num_classes"] == module.hparams.num_classes
    assert torch.equal(checkpoint[CHECKPOINT_KEY]["priors"], module.priors)
    assert checkpoint[CHECKPOINT_KEY]["data"] == module.data_config
