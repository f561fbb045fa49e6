"""``--network onnx:FILE`` (docs/definitions.md §19): networks of other libraries, exported by the
test with torch.onnx, against their own PyTorch forward; evaluate.py and predict.py end to end;
the refusals in one line."""

from __future__ import annotations

import json
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image
from test_networks import _randomise
from torch import nn

from costseg.classes import LABEL_ID_TO_TRAIN_ID
from costseg.cli import evaluate_main, predict_main
from costseg.costs import load_cost
from costseg.decision import decide_reference
from costseg.networks import load_network
from costseg.networks.base import IMAGENET_MEAN, IMAGENET_STD

pytest.importorskip("onnxruntime")
AXES = {0: "batch", 2: "height", 3: "width"}
ARGS = ["--no-progress", "--num_examples", "0", "--cost", "robotistic", "egoistic"]


def _export(net: nn.Module, path: Path, size=(64, 64), dynamic: bool = True, inputs=1) -> Path:
    """``net`` as ONNX (dynamic batch, height and width unless ``dynamic`` is False)."""
    names = [f"x{i}" for i in range(inputs)]
    args = tuple(torch.zeros(1, 3, *size) for _ in names)
    axes = {n: AXES for n in [*names, "y"]} if dynamic else None
    with warnings.catch_warnings(), torch.no_grad():
        warnings.simplefilter("ignore", DeprecationWarning)  # the TorchScript-based exporter
        torch.onnx.export(net.eval(), args, path, dynamo=False, input_names=names,
                          output_names=["y"], dynamic_axes=axes)  # fmt: skip
    return path


def _normalise(images: torch.Tensor) -> torch.Tensor:
    mean = torch.tensor(IMAGENET_MEAN).view(1, 3, 1, 1)
    return (images.float() / 255 - mean) / torch.tensor(IMAGENET_STD).view(1, 3, 1, 1)


class _MobileNetAtStride16(nn.Module):
    """torchvision's DeepLabV3-MobileNetV3 without its last upsampling: logits at 1/16."""

    def __init__(self) -> None:
        super().__init__()
        from torchvision.models.segmentation import deeplabv3_mobilenet_v3_large

        torch.manual_seed(0)
        self.model = deeplabv3_mobilenet_v3_large(
            weights=None, weights_backbone=None, num_classes=19
        ).eval()

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.model.classifier(self.model.backbone(x)["out"])


@pytest.fixture(scope="module")
def mobilenet(tmp_path_factory) -> tuple[nn.Module, Path]:
    net = _randomise(_MobileNetAtStride16())  # torchvision's initial logits hardly vary
    return net, _export(net, tmp_path_factory.mktemp("onnx") / "mobilenet.onnx")


def test_torchvision_network_at_a_fraction_of_the_size(mobilenet) -> None:
    """Upsampled bilinearly to the input size, the logits are torchvision's own forward."""
    net, path = mobilenet
    images = torch.randint(0, 256, (2, 3, 48, 80), dtype=torch.uint8)
    with torch.no_grad():
        expected = net.model(_normalise(images))["out"]
        got = load_network(f"onnx:{path}")(images)
        assert net(_normalise(images)).shape[-2:] == (3, 5)  # the graph's own output: 1/16
    torch.testing.assert_close(got, expected, atol=1e-4, rtol=1e-4)


def test_onnx_in_an_ensemble_and_a_sliding_window(mobilenet) -> None:
    """Two onnx: members (another normalisation for the second): the mean of their softmaxes;
    sliding windows reach the graph as smaller images, each resized to its window."""
    from costseg.networks.ensemble import open_sources
    from costseg.networks.protocols import Protocol

    _, path = mobilenet
    other = f"onnx:{path}?mean=0.5,0.5,0.5&std=0.25,0.25,0.25"
    images = torch.randint(0, 256, (1, 3, 48, 80), dtype=torch.uint8)
    cpu = torch.device("cpu")
    source = open_sources(None, [f"onnx:{path}", other], None, cpu, Protocol(), None, 0)
    with torch.no_grad():
        members = [load_network(spec)(images).softmax(1) for spec in (f"onnx:{path}", other)]
        torch.testing.assert_close(source.network(images), (members[0] + members[1]) / 2)
        assert (members[0] - members[1]).abs().max() > 1e-3  # the normalisation matters
        slide = Protocol(crop=(48, 48), stride=(48, 32))
        windows = open_sources(None, [f"onnx:{path}"], None, cpu, slide, None, 0)
        net = load_network(f"onnx:{path}")
        left, right = net(images[..., :48]), net(images[..., 32:])
        expected = torch.cat([left[..., :32], (left[..., 32:] + right[..., :16]) / 2,
                              right[..., 16:]], dim=-1)  # fmt: skip
        torch.testing.assert_close(windows.scores(images, ["a"]), expected)


def test_evaluate_onnx_equals_the_pytorch_forward_as_probs(mobilenet, cityscapes_root, tmp_path):
    """evaluate.py --network onnx:... gives the results of --probs files of PyTorch's logits."""
    net, path = mobilenet
    logits_dir = tmp_path / "logits"
    logits_dir.mkdir()
    for image in sorted((cityscapes_root / "leftImg8bit" / "val").glob("*/*.png")):
        x = torch.from_numpy(np.array(Image.open(image).convert("RGB"))).permute(2, 0, 1)[None]
        with torch.no_grad():
            logits = net.model(_normalise(x))["out"][0]
        stem = image.name.removesuffix("_leftImg8bit.png")
        np.savez(logits_dir / f"{stem}.npz", logits=logits.numpy())
    data = ["--data_root", str(cityscapes_root)]
    evaluate_main([*ARGS, *data, "--network", f"onnx:{path}", "--output_dir", str(tmp_path / "a")])
    evaluate_main([*ARGS, *data, "--probs", str(logits_dir), "--output_dir", str(tmp_path / "b")])
    first, second = (json.loads((tmp_path / d / "results.json").read_text()) for d in "ab")
    assert first["confusion_matrix"] == second["confusion_matrix"]
    assert first["miou"] == second["miou"] and first["rows"] == second["rows"]
    for key in ("nll", "brier"):
        assert first[key] == pytest.approx(second[key], rel=1e-5), key


def test_vainf_network_and_its_decision_graph_in_predict(vainf, tmp_path) -> None:
    """A VainF DeepLabV3+ through onnx: gives its logits; exported with the decision by
    scripts/export.py, predict.py --network onnx:graph decides as the reference on them."""
    from test_export import _script

    net, vainf_path = vainf
    path = _export(net, tmp_path / "vainf.onnx")
    images = torch.randint(0, 256, (1, 3, 48, 80), dtype=torch.uint8)
    with torch.no_grad():
        expected = load_network(f"vainf:{vainf_path}")(images)
        torch.testing.assert_close(
            load_network(f"onnx:{path}")(images), expected, atol=2e-4, rtol=0
        )
    graph = tmp_path / "graph.onnx"
    _script().main(["--network", f"vainf:{vainf_path}", "--output", str(graph), "--probabilities"])
    folder = tmp_path / "images"
    folder.mkdir()
    Image.fromarray(images[0].permute(1, 2, 0).numpy()).save(folder / "a.png")
    out, rules = tmp_path / "out", ["robotistic", "egoistic"]
    predict_main(["--input", str(folder), "--network", f"onnx:{graph}", "--cost", *rules,
                  "--save-probs", "--output_dir", str(out), "--no-progress"])  # fmt: skip
    saved = torch.from_numpy(np.load(out / "probs" / "a.npz")["probs"]).float()[None]
    torch.testing.assert_close(saved, expected.softmax(1), atol=1e-3, rtol=0)
    for rule in rules:
        ids = np.asarray(Image.open(out / "labels" / rule / "a.png"))
        reference = decide_reference(saved, load_cost(rule))[0].numpy()
        np.testing.assert_array_equal(LABEL_ID_TO_TRAIN_ID[ids], reference)


class _Two(nn.Module):
    def forward(self, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        return a + b


def test_onnx_refusals_are_one_line(cityscapes_root, tmp_path, capsys) -> None:
    seven = _export(nn.Conv2d(3, 7, 1), tmp_path / "seven.onnx")
    two = _export(_Two(), tmp_path / "two.onnx", inputs=2)
    fixed = _export(nn.Conv2d(3, 19, 1), tmp_path / "fixed.onnx", size=(16, 24), dynamic=False)
    (tmp_path / "text.onnx").write_text("not a graph")
    cases = {
        f"onnx:{seven}": f"{seven} gives 7 classes (output batch x 7 x height x width)",
        f"onnx:{two}": f"{two} has 2 inputs (x0, x1); expected one image input",
        f"onnx:{fixed}": f"{fixed} accepts only 16 x 24 (H x W) images; got 32 x 64",
        f"onnx:{tmp_path / 'text.onnx'}": f"{tmp_path / 'text.onnx'} is not a readable ONNX",
        f"onnx:{seven}?mean=1,2": "bad mean in",
        f"onnx:{seven}?scale=2": "bad option scale=2",
        "onnx:missing.onnx": "not found: missing.onnx",
    }
    for i, (spec, message) in enumerate(cases.items()):  # a refusal met in the run leaves its
        with pytest.raises(SystemExit) as exit_:  # folder marked INCOMPLETE: one folder each
            evaluate_main([*ARGS, "--data_root", str(cityscapes_root), "--network", spec,
                           "--output_dir", str(tmp_path / f"out{i}")])  # fmt: skip
        err = capsys.readouterr().err
        assert exit_.value.code == 2 and err.count("\n") == 1, err
        assert err.startswith(f"error: {message}"), err
