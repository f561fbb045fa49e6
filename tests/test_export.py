"""The exported decision graph (docs/definitions.md §19): onnxruntime's labels against the float64
reference decision on PyTorch's probabilities, the matrix changed at run time, the uint8 input
against the normalised float path, scripts/export.py's refusals."""

from __future__ import annotations

import importlib.util
import re
import warnings
from pathlib import Path

import pytest
import torch
from torch import nn

from costseg.costs import load_cost, symmetric_cost, with_defer
from costseg.decision import decide_reference
from costseg.decision.reference import shift
from costseg.export.graph import DecisionGraph
from costseg.export.job import trace_graph
from costseg.export.parity import parity
from costseg.export.runtime import run_graph
from costseg.networks import load_network
from costseg.networks.base import IMAGENET_MEAN, IMAGENET_STD, ImageNetwork, normalised
from costseg.networks.onnx import onnx_session

pytest.importorskip("onnxruntime")
SCRIPT = Path(__file__).resolve().parents[1] / "scripts" / "export.py"
SIZE = (40, 56)


def _network(seed: int = 0) -> ImageNetwork:
    """Random logits of a few units at half the input size (resized as every network's are)."""
    torch.manual_seed(seed)
    net = nn.Sequential(nn.Conv2d(3, 16, 3, padding=1), nn.Tanh(), nn.Conv2d(16, 19, 2, stride=2))
    with torch.no_grad():
        net[2].weight.mul_(8)
    return ImageNetwork(net)


@pytest.fixture(scope="module")
def graph():
    """The network, its exported graph (with probabilities) and an onnxruntime session of it."""
    network = _network()
    model = trace_graph(DecisionGraph(network, probabilities=True))
    return network, model, onnx_session(model.SerializeToString(), threads=1)


def _images(size=SIZE, batch: int = 2, seed: int = 3) -> torch.Tensor:
    gen = torch.Generator().manual_seed(seed)
    return torch.randint(0, 256, (batch, 3, *size), generator=gen, dtype=torch.uint8)


def _rules(size=SIZE) -> dict[str, tuple[torch.Tensor, torch.Tensor | None]]:
    """robotistic, altruistic, egoistic, ML with pixel priors, Chow's rule deferring at 0.5."""
    gen = torch.Generator().manual_seed(5)
    priors = torch.rand((19, *size), generator=gen) ** 4 + 1e-3  # also rare classes, none at 0
    priors = priors / priors.sum(0)
    rules = {name: (load_cost(name), None) for name in ("robotistic", "altruistic", "egoistic")}
    rules["ml"] = (symmetric_cost(19), priors)
    rules["defer"] = (with_defer(symmetric_cost(19), 0.5), None)
    return rules


def _costs64(probs: torch.Tensor, cost: torch.Tensor, priors) -> torch.Tensor:
    """(B, M, H, W) float64 expected costs under the shifted matrix (the reference's)."""
    q = probs.double() / (1.0 if priors is None else priors.double())
    return torch.einsum("jk,bkhw->bjhw", shift(cost.double()), q)


def test_labels_are_the_reference_under_every_matrix_of_one_graph(graph) -> None:
    network, _, session = graph
    images = _images()
    with torch.no_grad():
        torch_probs = network(images).softmax(1)
    decided = {}
    for name, (cost, priors) in _rules().items():
        labels, margin, probs = run_graph(session, images, cost, priors, probabilities=True)
        torch.testing.assert_close(probs, torch_probs, atol=1e-6, rtol=0)
        assert labels.dtype == torch.uint8 and margin.dtype == torch.float32
        result = parity(torch_probs, probs, labels, cost, priors)
        assert result.outside == 0, name
        # Zero differences away from near ties (the two best costs 1e-4 of the scale apart).
        costs = _costs64(torch_probs, cost, priors)
        best = costs.topk(2, dim=1, largest=False).values
        near = (best[:, 1] - best[:, 0]) < 1e-4 * costs.abs().amax(1)
        reference = decide_reference(torch_probs, cost, priors)
        assert torch.equal(labels.long()[~near], reference[~near]), name
        # The margin: second smallest minus smallest expected cost.
        scale = costs.abs().amax(1)
        assert ((margin.double() - (best[:, 1] - best[:, 0])).abs() <= 1e-5 * scale).all(), name
        decided[name] = labels
    assert (decided["defer"] == 255).any() and (decided["defer"] != 255).any()
    for name in ("altruistic", "egoistic", "ml"):  # the matrix given at run time decides
        assert not torch.equal(decided[name], decided["robotistic"]), name


def test_a_label_beyond_the_bound_is_caught() -> None:
    p = torch.tensor([0.6, 0.4]).view(1, 2, 1, 1)
    near = torch.tensor([0.5, 0.5 + 1e-9]).view(1, 2, 1, 1)
    cost = symmetric_cost(2)
    assert parity(p, p, torch.tensor([[[1]]]), cost).outside == 1  # 0.2 apart: wrong
    assert parity(near, near, torch.tensor([[[0]]]), cost).outside == 0  # a near tie: allowed
    # A probability map that differs explains the label the graph gives.
    assert parity(p, near.flip(1), torch.tensor([[[0]]]), cost).outside == 0


def test_uint8_graph_equals_the_normalised_float_path(graph, tmp_path) -> None:
    """The graph normalises inside; a float-input export of the same network, normalised by
    ``onnx:...?mean=&std=``, gives the same probabilities, and both those of PyTorch."""
    network, _, session = graph
    path = tmp_path / "float.onnx"
    axes = {0: "batch", 2: "height", 3: "width"}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)  # the TorchScript-based exporter
        torch.onnx.export(network.net, (torch.zeros(1, 3, *SIZE),), path, dynamo=False,
                          input_names=["x"], output_names=["y"],
                          dynamic_axes={"x": axes, "y": axes})  # fmt: skip
    mean, std = ",".join(map(str, IMAGENET_MEAN)), ",".join(map(str, IMAGENET_STD))
    floats = load_network(f"onnx:{path}?mean={mean}&std={std}")
    images = _images((34, 50), batch=3)
    _, _, probs = run_graph(session, images, symmetric_cost(19), probabilities=True)
    with torch.no_grad():
        torch.testing.assert_close(floats(images).softmax(1), probs, atol=1e-6, rtol=0)
        x = normalised(images, network.mean, network.std)
        reference = nn.functional.interpolate(network.net(x), size=(34, 50), mode="bilinear")
        torch.testing.assert_close(probs, reference.softmax(1), atol=1e-6, rtol=0)


def test_temperature_and_global_priors_are_inputs(graph) -> None:
    network, _, session = graph
    images = _images((24, 32), batch=1)
    pi = torch.rand(19, generator=torch.Generator().manual_seed(2)) + 1e-2
    labels, _, probs = run_graph(session, images, symmetric_cost(19), pi, 2.5, probabilities=True)
    with torch.no_grad():
        expected = (network(images) / 2.5).softmax(1)
    torch.testing.assert_close(probs, expected, atol=1e-6, rtol=0)
    assert parity(expected, probs, labels, symmetric_cost(19), pi).outside == 0


def _script():
    spec = importlib.util.spec_from_file_location("export_script", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--ckpt_path", "a.ckpt", "b.ckpt"], "an ensemble (2 sources) has no single graph"),
        (["--network", "vainf:a.pth", "vainf:b.pth"], "an ensemble (2 sources)"),
        (["--ckpt_path", "a.ckpt", "--mc_dropout", "4"], "Monte-Carlo dropout has no single"),
        (["--network", "onnx:m.onnx"], "onnx:m.onnx is an ONNX file already"),
        (["--ckpt_path", "missing.ckpt"], "checkpoint not found: missing.ckpt"),
        (["--network", "vainf:x.pth?os=3"], "bad option 'os=3'"),
        (["--probabilites"], "export.py: unrecognized arguments: --probabilites"),
        (["--mc_dropout", "0"], "export.py: argument --mc_dropout: expected a whole number >= 1"),
    ],
)
def test_export_refusals_are_one_line(args, message, tmp_path, capsys) -> None:
    with pytest.raises(SystemExit) as exit_:
        _script().main([*args, "--output", str(tmp_path / "m.onnx")])
    err = capsys.readouterr().err
    assert exit_.value.code == 2 and err.count("\n") == 1 and err.startswith(f"error: {message}")


def test_export_never_overwrites_silently(tmp_path, capsys) -> None:
    (tmp_path / "m.json").write_text("{}")
    with pytest.raises(SystemExit):
        _script().main(["--ckpt_path", "a.ckpt", "--output", str(tmp_path / "m.onnx")])
    assert capsys.readouterr().err == (
        f"error: {tmp_path / 'm.json'} exists: choose another --output or add --overwrite\n"
    )
    assert (tmp_path / "m.json").read_text() == "{}"


def test_exported_graph_of_a_costseg_checkpoint(tiny_run, tmp_path, capsys) -> None:
    """The whole command: graph, sidecar and priors (in the format --priors reads); the graph
    decides ML with the stored priors as the reference does on PyTorch's probabilities."""
    import json

    from costseg.classes import CLASS_NAMES
    from costseg.data.priors import read_priors_file
    from costseg.networks import load_costseg_checkpoint

    path = next(Path(tiny_run[2]).glob("**/last.ckpt"))
    out = tmp_path / "m.onnx"
    _script().main(["--ckpt_path", str(path), "--output", str(out), "--probabilities"])
    printed = capsys.readouterr().out.splitlines()
    priors_file = out.with_suffix(".priors.pt")
    assert (
        printed[1]
        == f"wrote {priors_file}: the checkpoint's priors (evaluate.py --priors reads it)"
    )
    parity_line = r"parity at 72 x 136 against PyTorch \(docs/definitions.md §19\): [\d,]+ of "
    assert re.fullmatch(
        parity_line + r"9,792 labels differ, 0 beyond the float32 bound", printed[2]
    )
    sidecar = json.loads(out.with_suffix(".json").read_text())
    assert sidecar["priors"] == priors_file.name
    checkpoint = load_costseg_checkpoint(path)
    priors = read_priors_file(priors_file, CLASS_NAMES)["priors"]  # what --priors reads
    assert torch.equal(priors, checkpoint.priors.float())
    assert sidecar["rules"]["ml"]["priors"] and not sidecar["rules"]["egoistic"]["priors"]
    assert sidecar["outputs"].keys() == {"labels", "margin", "probabilities"}
    images = _images(tuple(priors.shape[1:]), batch=1)
    cost = torch.tensor(sidecar["rules"]["egoistic"]["cost"])
    labels, _, probs = run_graph(onnx_session(out), images, cost, priors, probabilities=True)
    with torch.no_grad():
        torch_probs = checkpoint.network(images).softmax(1)
    assert parity(torch_probs, probs, labels, cost, priors).outside == 0
