"""The exported graph of a regional value system (docs/definitions.md §19, §21): onnxruntime's
labels against a loop over the RoIs calling the float64 reference with each RoI's matrix on
PyTorch's probabilities, within the float32 bound; a plain matrix through the same graph; the
RoI map refused in one line when it does not fit; the whole command on the tiny checkpoint."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest
import torch
from test_export import _images, _network, _script

from costseg.costs import COSTS_DIR, load_cost, symmetric_cost, with_defer
from costseg.decision import decide_reference
from costseg.decision.reference import shift
from costseg.export.graph import DecisionGraph, graph_roi
from costseg.export.job import trace_graph
from costseg.export.parity import parity
from costseg.export.runtime import run_graph
from costseg.networks import load_network
from costseg.networks.onnx import onnx_session

pytest.importorskip("onnxruntime")
SIZE = (40, 56)
STREET = load_cost(COSTS_DIR / "street_person.yaml")


@pytest.fixture(scope="module")
def regional():
    """The network, its regional graph (with probabilities) and an onnxruntime session."""
    network = _network()
    model = trace_graph(DecisionGraph(network, probabilities=True, regional=True))
    return network, onnx_session(model.SerializeToString(), threads=1)


def _stacks() -> dict[str, torch.Tensor]:
    five = torch.stack([*(load_cost(n) for n in ("robotistic", "altruistic", "egoistic")),
                        STREET[1], 3 * symmetric_cost(19)])  # fmt: skip
    deferring = torch.stack([with_defer(m, 0.2 * (r + 1)) for r, m in enumerate(five)])
    return {"five": five, "street_person": STREET, "defer": deferring}


def _roi(size, seed: int = 7) -> torch.Tensor:
    """(h, w) uint8 RoI ids 0 … 4 in rectangles."""
    coarse = torch.randint(0, 5, (1, 1, 3, 4), generator=torch.Generator().manual_seed(seed))
    return torch.nn.functional.interpolate(coarse.float(), size=size)[0, 0].to(torch.uint8)


def _loop(probs: torch.Tensor, stack: torch.Tensor, roi: torch.Tensor) -> torch.Tensor:
    """The independent reference: each RoI's pixels by ``decide_reference`` with its matrix."""
    out = torch.full((len(probs), *roi.shape), -1, dtype=torch.long)
    for r in range(len(stack)):
        mine = (roi == r).expand_as(out)
        out[mine] = decide_reference(probs, stack[r])[mine]
    return out


def _near_ties(probs, stack, roi) -> torch.Tensor:
    """(B, H, W) where the reference's two best costs lie within 1e-4 of the costs' scale."""
    costs = torch.stack([torch.einsum("jk,bkhw->bjhw", shift(m), probs.double()) for m in stack])
    mine = costs.gather(0, roi.long().view(1, 1, 1, *roi.shape).expand(1, *costs.shape[1:]))[0]
    best = mine.topk(2, dim=1, largest=False).values
    return (best[:, 1] - best[:, 0]) < 1e-4 * mine.abs().amax(1)


@pytest.mark.parametrize("name", ["five", "street_person", "defer"])
def test_labels_are_a_loop_over_the_rois_within_the_bound(regional, name) -> None:
    network, session = regional
    images, stack = _images(SIZE), _stacks()[name]
    roi = _roi((SIZE[0] // 2, SIZE[1] // 2))  # a map at another size: resized in the graph
    labels, _, probs = run_graph(session, images, stack, probabilities=True, roi=roi)
    with torch.no_grad():
        torch_probs = network(images).softmax(1)
    resized = graph_roi(roi, SIZE).view(SIZE)
    assert torch.equal(resized, torch.nn.functional.interpolate(roi[None, None], size=SIZE)[0, 0])
    assert parity(torch_probs, probs, labels, stack, roi=resized).outside == 0
    expected, near = _loop(torch_probs, stack, resized), _near_ties(torch_probs, stack, resized)
    assert torch.equal(labels.long()[~near], expected[~near])
    assert len(set(resized.unique().tolist())) > 2  # several regions decided


def test_one_matrix_through_the_regional_graph_is_the_plain_rule(regional) -> None:
    network, session = regional
    images, cost = _images(SIZE), load_cost("egoistic")
    zeros = torch.zeros(1, 1, dtype=torch.uint8)
    labels, margin = run_graph(session, images, cost[None], roi=zeros)
    plain = trace_graph(DecisionGraph(network, probabilities=True))
    expected, expected_margin = run_graph(onnx_session(plain.SerializeToString()), images, cost)
    assert torch.equal(labels, expected) and torch.equal(margin, expected_margin)


@pytest.mark.parametrize(
    ("roi", "message"),
    [
        (torch.zeros(56, 40, dtype=torch.uint8), r"the RoI map is 56 x 40 and the images 40 x 56"),
        (torch.zeros(10, 28, dtype=torch.uint8), r"the RoI map is 10 x 28 and the images 40 x 56"),
        (torch.full((20, 28), 5, dtype=torch.uint8), r"holds id 5; the stack has matrices 0 … 4"),
        (torch.zeros(2, 20, 28, dtype=torch.uint8), r"must be \(h, w\), got \(2, 20, 28\)"),
        (None, "a regional graph takes a stack of matrices"),
    ],
)
def test_a_roi_map_that_does_not_fit_is_refused_in_one_line(regional, roi, message) -> None:
    with pytest.raises(ValueError, match=message) as err:
        run_graph(regional[1], _images(SIZE), STREET, roi=roi)
    assert "\n" not in str(err.value)


def test_a_plain_graph_refuses_a_stack() -> None:
    plain = DecisionGraph(_network(), probabilities=True)
    session = onnx_session(trace_graph(plain).SerializeToString())
    with pytest.raises(
        ValueError, match=r"this graph takes one matrix: .* exported with --regional"
    ):
        run_graph(session, _images(SIZE), STREET, roi=torch.zeros(20, 28, dtype=torch.uint8))


def test_exported_regional_graph_of_a_costseg_checkpoint(tiny_run, tmp_path, capsys) -> None:
    path = next(Path(tiny_run[2]).glob("**/last.ckpt"))
    out = tmp_path / "m.onnx"
    _script().main(["--ckpt_path", str(path), "--output", str(out), "--regional",
                    "--probabilities"])  # fmt: skip
    printed = capsys.readouterr().out
    assert re.search(r"parity at 72 x 136 .*, 0 beyond the float32 bound", printed), printed
    sidecar = json.loads(out.with_suffix(".json").read_text())
    assert sidecar["regional"] and "roi" in sidecar["inputs"]
    source = load_network(f"onnx:{out}")  # the graph as a probability source: RoI 0 everywhere
    images = _images((64, 128), batch=1)
    from costseg.networks import load_costseg_checkpoint

    checkpoint = load_costseg_checkpoint(path)
    with torch.no_grad():
        torch.testing.assert_close(
            source(images).softmax(1), checkpoint.network(images).softmax(1), atol=1e-5, rtol=0
        )
