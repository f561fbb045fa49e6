"""The dispatcher: which path takes an input, why the others do not, and forcing a path."""

import pytest
import torch
from decision_inputs import VERTICES

from costseg.costs import barycentric_grid
from costseg.decision import decide, decide_mixtures, decide_reference, explain
from costseg.decision.cpu import VERTICES as MOST_VERTICES
from costseg.decision.cpu import numba_path
from costseg.decision.dispatch import ENV, PATHS, choose, reasons
from costseg.decision.inputs import Inputs

SMALL = torch.rand(1, 19, 4, 5, generator=torch.Generator().manual_seed(0)).softmax(1)


@pytest.fixture(autouse=True)
def automatic(monkeypatch):
    monkeypatch.delenv(ENV, raising=False)
    monkeypatch.delenv("TRITON_INTERPRET", raising=False)


def inputs(shape=(1, 19, 4, 5), device="cpu", pixel_priors=False, vertices=1, mixtures=None):
    return Inputs(shape, torch.device(device), torch.float32, pixel_priors, vertices, mixtures)


def test_the_priority_list_and_its_choices_on_the_cpu():
    assert list(PATHS) == ["triton", "numba", "torch", "reference"]
    assert choose(inputs()).NAME == "torch"  # a small image: numba does not pay off
    big = inputs(shape=(1, 19, 1024, 1024))
    assert choose(big).NAME == "numba"
    assert choose(inputs(vertices=3, mixtures=66)).NAME == "numba"
    assert choose(inputs(vertices=3, mixtures=3)).NAME == "torch"  # a few named rules
    assert choose(inputs(vertices=MOST_VERTICES + 1, mixtures=66)).NAME == "torch"


def test_each_path_says_why_it_cannot_take_an_input():
    on_cpu = reasons("triton", inputs())
    assert any("no CUDA device" in r or "not installed" in r for r in on_cpu), on_cpu
    assert any("pixel-wise priors" in r for r in reasons("triton", inputs(pixel_priors=True)))
    assert any("run on the CPU" in r for r in reasons("numba", inputs(device="cuda")))
    assert any("at most 3" in r for r in reasons("numba", inputs(vertices=4, mixtures=9)))
    assert any("pays off" in r or "pay off" in r for r in reasons("numba", inputs()))
    assert reasons("numba", inputs(), automatic=False) == []  # forcing ignores preferences
    assert reasons("torch", inputs(device="cuda", pixel_priors=True)) == []
    assert reasons("reference", inputs(device="cuda", pixel_priors=True)) == []


def test_forcing_a_path_that_cannot_take_the_input_raises_with_its_reasons(monkeypatch):
    with pytest.raises(ValueError, match=r"decision path 'triton' cannot take .*no CUDA device"):
        decide(SMALL, VERTICES[2], path="triton")
    vertices = torch.cat([VERTICES, VERTICES[:1]])
    with pytest.raises(ValueError, match=r"'numba' cannot take .* the kernel mixes at most 3"):
        decide_mixtures(SMALL, vertices, torch.ones(5, 4), path="numba")
    with pytest.raises(ValueError, match="unknown decision path 'fast'"):
        decide(SMALL, None, path="fast")
    monkeypatch.setenv(ENV, "triton")
    with pytest.raises(ValueError, match="'triton' cannot take"):
        decide(SMALL, None)


def test_the_environment_variable_and_the_argument_force_a_path(monkeypatch):
    calls = []
    original = numba_path.decide
    monkeypatch.setattr(numba_path, "decide", lambda *a: calls.append(1) or original(*a))
    expected = decide_reference(SMALL, VERTICES[1])
    assert torch.equal(decide(SMALL, VERTICES[1], path="numba"), expected) and calls == [1]
    monkeypatch.setenv(ENV, "numba")
    assert torch.equal(decide(SMALL, VERTICES[1]), expected) and calls == [1, 1]
    monkeypatch.setenv(ENV, "reference")
    assert torch.equal(decide(SMALL, VERTICES[1]), expected) and calls == [1, 1]
    mixed = decide_mixtures(SMALL, VERTICES, barycentric_grid(0.5))
    assert mixed.dtype == torch.uint8  # as every path returns them


def test_explain_names_the_path_and_every_reason(monkeypatch):
    text = explain(SMALL, VERTICES[2])
    assert text.splitlines()[0].endswith("path 'torch'")
    assert "numba: not chosen: 20 pixels per image" in text and "torch: taken" in text
    assert "triton: cannot:" in text and "reference: fits" in text
    text = explain(SMALL, VERTICES, weights=barycentric_grid(0.1))
    assert text.startswith("decide_mixtures (66 mixtures of 3 vertices)") and "numba: taken" in text
    monkeypatch.setenv(ENV, "reference")
    assert f"path 'reference' (forced by {ENV})" in explain(SMALL)
    with pytest.raises(ValueError, match="priors must be"):
        explain(SMALL, None, torch.ones(3))
