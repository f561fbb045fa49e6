"""The explorer page in a real browser (headless Chromium): its masks at any point of the
triangle and any defer cost equal the float64 reference on the embedded float16 probabilities,
pixel for pixel. Chromium starts once per test: one launch opens many states (states_page)."""

from __future__ import annotations

import base64
import hashlib
import html
import json
import re
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest
import torch
from explorer_page import embedded_probs, page_json, states_page

from costseg.classes import CLASS_NAMES
from costseg.costs import barycentric_grid, mix_costs, with_defer
from costseg.decision import decide_reference
from costseg.report.explorer import Marks, SweepData, embedded, write_explorer
from costseg.rules import vertex_matrices

CHROMIUM = next(
    (p for p in map(shutil.which, ("chromium", "chromium-browser", "google-chrome")) if p), None
)
needs_chromium = pytest.mark.skipif(
    CHROMIUM is None, reason="chromium not found: apt-get install chromium to run the browser tests"
)
VERTEX_NAMES = ["robotistic", "altruistic", "egoistic"]
WEIGHTS = ["1,0,0", "0,0,1", "0.5,0.25,0.25", "0.123,0.456,0.421", "0.05,0.9,0.05"]
TIE = 0.5  # robotistic (Chow): deferring at 0.5 costs as much as person or car where both are 0.5
ULP = 2.0**-53  # 0.5 ± ULP: deferring a hair cheaper / dearer than the tied classes
DEFER_STATES = [("0.123,0.456,0.421", 0.37), ("0.05,0.9,0.05", 2.5), ("0,0,1", 0.0),
                ("0.5,0.25,0.25", 1000.0), ("1,0,0", TIE - ULP), ("1,0,0", TIE),
                ("1,0,0", TIE + ULP)]  # fmt: skip


def browser(page: Path, fragment: str, *extra: str) -> str:
    """Chromium's DOM of ``page#fragment`` once its scripts ran (or its output with ``extra``)."""
    args = [CHROMIUM, "--headless", "--no-sandbox", "--disable-gpu", "--virtual-time-budget=30000",
            "--allow-file-access-from-files"]  # fmt: skip
    out = subprocess.run(
        [*args, *(extra or ("--dump-dom",)), f"{page.as_uri()}#{fragment}"],
        capture_output=True,
        text=True,
        timeout=180,
    )
    return out.stdout


def page_states(page: Path, steps: list) -> list[dict]:
    """What each step of :func:`explorer_page.states_page` showed, in one Chromium launch."""
    dom = browser(states_page(page.parent, steps), "")
    found = re.search(r'<pre id="states">(.*?)</pre>', dom, re.S)
    assert found and found.group(1), "the states page listed nothing"
    return json.loads(html.unescape(found.group(1)))


def reference_labels(probs: torch.Tensor, weights: list[float], defer=None) -> np.ndarray:
    """decide_reference with the mixed matrix (and a defer row ``defer``) as uint8."""
    vertices = vertex_matrices(VERTEX_NAMES)
    w = torch.tensor([weights], dtype=torch.float64)
    mixed = mix_costs(vertices, w)[0]
    # the page mixes (w0*C0 + w1*C1) + w2*C2; mix_costs must round the same way
    assert torch.equal(
        mixed, (w[0, 0] * vertices[0] + w[0, 1] * vertices[1]) + w[0, 2] * vertices[2]
    )
    cost = mixed if defer is None else with_defer(mixed, defer)
    return decide_reference(probs[None], cost)[0].numpy().astype(np.uint8)


def assert_reference_masks(state: dict, probs: dict[str, torch.Tensor]) -> None:
    """The page's masks (and deferred pixels) of every example equal the reference's."""
    assert [e["name"] for e in state["examples"]] == list(probs)
    for example in state["examples"]:
        p = probs[example["name"]]
        assert (example["height"], example["width"]) == tuple(p.shape[1:])
        labels = reference_labels(p, state["w"], state["defer"])
        sha = hashlib.sha256(labels.tobytes()).hexdigest()
        assert example["labels_sha256"] == sha, (example["name"], state["w"], state["defer"])
        assert example["deferred_pixels"] == np.count_nonzero(labels == 255)


def synthetic_probs(h: int, w: int, seed: int) -> torch.Tensor:
    """(19, H, W) probabilities with confident, spread-out and exactly tied pixels."""
    g = torch.Generator().manual_seed(seed)
    logits = torch.randn(19, h, w, generator=g) * torch.linspace(0.5, 6, w)
    probs = logits.softmax(0)
    probs[:, : h // 4, : w // 4] = 1 / 19  # every class tied
    probs[:, -3:, :] = 0
    probs[[11, 13], -3:, :] = 0.5  # person and car tied
    return probs


@pytest.fixture(scope="module")
def page(tmp_path_factory) -> Path:
    """A page of three synthetic examples (one larger than 256 × 512) and a 0.25 sweep."""
    examples = [
        embedded(f"ex{i}", np.full((h, w, 3), 40 * i, np.uint8), synthetic_probs(h, w, i))
        for i, (h, w) in enumerate([(32, 48), (17, 29), (300, 530)])
    ]
    weights = barycentric_grid(0.25)
    values = torch.linspace(0, 1, len(weights)).tolist()
    sweep = SweepData(weights.tolist(), {"recall": {"person": {"1": values}}}, "test sweep")
    marks = Marks(targets=[("t", weights[3].tolist())], certified=[("c", weights[4].tolist())])
    path = tmp_path_factory.mktemp("explorer") / "explorer.html"
    named = [(n, [float(i == v) for i in range(3)]) for v, n in enumerate(VERTEX_NAMES)]
    return write_explorer(
        path, examples, vertex_matrices(VERTEX_NAMES), VERTEX_NAMES, named, sweep, marks
    )


def test_large_examples_are_embedded_at_reduced_resolution(page):
    probs = embedded_probs(page)
    assert tuple(probs["ex2"].shape) == (19, 150, 265)
    assert "every 2nd pixel of the 300 × 530 image" in page.read_text()


@needs_chromium
def test_page_masks_equal_the_reference_with_and_without_deferring(page):
    steps = [(page, f"w={w}", None) for w in WEIGHTS]
    steps += [(page, f"w={w}&defer={d!r}", None) for w, d in DEFER_STATES]
    states = [s["state"] for s in page_states(page, steps)]
    probs = embedded_probs(page)
    expected = [(w, None) for w in WEIGHTS] + DEFER_STATES
    for state, (weights, defer) in zip(states, expected, strict=True):
        assert state["w"] == [float(x) for x in weights.split(",")]
        assert state["defer"] == defer
        assert_reference_masks(state, probs)
    # the near tie is one: where person and car are 0.5 each, the page's masks above hold
    tied = probs["ex0"][:, -3:]  # deferring at 0.5 ties with both (the reference decides so)
    assert (reference_labels(tied, [1, 0, 0], TIE - ULP) == 255).all()
    assert (reference_labels(tied, [1, 0, 0], TIE) == 11).all()  # a class wins the tie
    assert (reference_labels(tied, [1, 0, 0], TIE + ULP) == 11).all()


@pytest.fixture(scope="module")
def deferring_page(tmp_path_factory) -> Path:
    """A page of one example that opens with the defer cost 0.3 (``--defer 0.3``)."""
    example = embedded("ex0", np.zeros((32, 48, 3), np.uint8), synthetic_probs(32, 48, 0))
    path = tmp_path_factory.mktemp("explorer_defer") / "explorer.html"
    return write_explorer(path, [example], vertex_matrices(VERTEX_NAMES), VERTEX_NAMES, defer=0.3)


@needs_chromium
def test_defer_in_the_url_round_trips(page, deferring_page):
    a, b = page, deferring_page
    steps = [(b, "w=0,1,0", None), (b, "w=0,1,0&defer=off", None), (b, "w=0,1,0&defer=-1", None),
             (b, "w=0,1,0&defer=abc", None), (b, "w=0,1,0&defer=", None),
             (a, "w=1,0,0&defer=nan", None),
             (b, "w=0,0,1", 120), (None, "", None),  # the slider, then its URL opened again
             (b, "w=0,0,1&defer=0.7", -1), (None, "", None),  # the slider's "off"
             (a, "w=1,0,0&defer=0.5", -1), (None, "", None)]  # fmt: skip
    shown = page_states(page, steps)
    states = [s["state"] for s in shown]
    defers = [s["defer"] for s in states]
    assert defers[:6] == [0.3, None, 0.3, 0.3, 0.3, None]  # the default; invalid ones ignored
    slid = re.fullmatch(r"#w=0,0,1&defer=([^&]+)", shown[6]["hash"])
    assert slid and float(slid.group(1)) == defers[6] and 0 < defers[6] <= 1000
    assert states[7] == {**states[6], "ms": states[7]["ms"]}  # the same state from its URL
    assert [s["hash"] for s in shown[8:]] == ["#w=0,0,1&defer=off"] * 2 + ["#w=1,0,0"] * 2
    assert defers[8:] == [None] * 4
    probs, opened = {a: embedded_probs(a), b: embedded_probs(b)}, []
    for where, _, _ in steps:  # None: the page of the step before
        opened.append(where or opened[-1])
    for where, state, step in zip(opened, states, shown, strict=True):
        assert_reference_masks(state, probs[where])
        total = sum(e["height"] * e["width"] for e in state["examples"])
        deferred = sum(e["deferred_pixels"] for e in state["examples"])
        if state["defer"] is not None:
            percent = float(re.search(r"deferred ([0-9.]+) %", step["shown"]).group(1))
            assert abs(percent - 100 * deferred / total) <= 0.05 + 1e-9


@needs_chromium
def test_screenshot_shows_the_triangle_and_the_masks(page, tmp_path):
    from PIL import Image

    shot = tmp_path / "shot.png"
    browser(page, "w=0.5,0.25,0.25", f"--screenshot={shot}", "--window-size=1400,900")
    image = np.asarray(Image.open(shot).convert("RGB")).astype(np.int64)
    colours = lambda a: len(np.unique(a.reshape(-1, 3), axis=0))  # noqa: E731
    triangle, masks = image[80:420, 40:420], image[80:400, 470:1300]
    assert colours(triangle) > 8 and triangle.std() > 20  # the heatmap and the marks
    assert colours(masks) > 8 and masks.std() > 20


@needs_chromium
def test_evaluate_explorer_holds_the_sweep_and_reference_masks(tiny_run, tmp_path):
    from costseg.checkpoints import find_checkpoint
    from costseg.cli import evaluate_main

    out = tmp_path / "evaluation"
    ckpt = find_checkpoint(None, runs_dir=tiny_run[2])
    evaluate_main(["--ckpt_path", str(ckpt), "--output_dir", str(out), "--sweep", "0.5",
                   "--limit", "2", "--num_examples", "2", "--explorer", "--no-progress",
                   "--target", "road:roi0:recall>=0.0", "--maximize", "road:roi0:recall",
                   "--classes", "road"])  # fmt: skip
    page = out / "explorer.html"
    text = page.read_text()
    assert '"sweep":{"weights":[[1.0,0.0,0.0]' in text and '"targets":[{"label"' in text
    probs = embedded_probs(page)
    assert len(probs) == 2
    shown = {"0.5,0.5,0": "swept metrics", "0.3,0.3,0.4": "over the 2 embedded examples",
             "0.5,0.5,0&defer=0.2": "a deferred pixel is not predicted as any class"}  # fmt: skip
    steps = [(page, f"w={fragment}", None) for fragment in shown]
    for step, metrics in zip(page_states(page, steps), shown.values(), strict=True):
        assert metrics in step["metrics"]  # a grid point, between grid points, deferring
        assert_reference_masks(step["state"], probs)


HOVER = """<!DOCTYPE html><pre id="out"></pre><script>
const frame = document.createElement("iframe");
frame.onload = () => {
  const doc = frame.contentDocument, win = frame.contentWindow;
  const canvas = doc.querySelector(".example canvas"), rect = canvas.getBoundingClientRect();
  const [y, x] = %s, scale = rect.width / canvas.width;
  canvas.dispatchEvent(new win.MouseEvent("mousemove",
    {clientX: rect.left + (x + 0.5) * scale, clientY: rect.top + (y + 0.5) * scale}));
  document.getElementById("out").textContent = doc.getElementById("hover").textContent;
};
frame.src = %s;
document.body.appendChild(frame);
</script>"""
"""A page that hovers pixel (y, x) of the first example of an explorer page and lists what the
page's hover box then shows."""


@needs_chromium
def test_hovering_a_pixel_shows_its_uncertainty(tmp_path):
    g = torch.Generator().manual_seed(0)
    probs = torch.rand(19, 6, 8, generator=g).softmax(0)
    maps = {"entropy": torch.rand(6, 8, generator=g) * 3, "mutual_information": torch.rand(6, 8)}
    example = embedded("ex", np.zeros((6, 8, 3), np.uint8), probs, uncertainty=maps)
    page = write_explorer(
        tmp_path / "explorer.html", [example], vertex_matrices(VERTEX_NAMES), VERTEX_NAMES
    )
    carried = page_json(page)["examples"][0]["uncertainty"]
    for key, value in maps.items():  # the page carries the maps as float16
        half = np.frombuffer(base64.b64decode(carried[key]), "<f2").reshape(6, 8)
        np.testing.assert_array_equal(half, value.half().numpy())
    hover = tmp_path / "hover.html"
    hover.write_text(HOVER % ("[4, 5]", json.dumps(page.as_uri())))
    dom = browser(hover, "")
    shown = re.search(r"entropy ([\d.e+-]+), mutual information ([\d.e+-]+) nats", dom)
    assert shown, dom[-500:]
    for value, key in zip(shown.groups(), ("entropy", "mutual_information"), strict=True):
        assert float(value) == pytest.approx(float(maps[key].half()[4, 5]), rel=5e-3)  # 3 digits


@needs_chromium
def test_the_page_shows_a_class_legend_no_debug_output_and_only_menus_that_act(page, tmp_path):
    """A page with a sweep: its heatmap menus; one with labels but no sweep (evaluate.py without
    --sweep): the class of its metrics, which changes them; one without either (predict.py):
    no menu. Each: every class in the legend, and no state JSON or timing shown."""
    g = torch.Generator().manual_seed(1)
    labels = torch.randint(0, 19, (6, 8), generator=g).numpy().astype(np.uint8)
    probs = torch.rand(19, 6, 8, generator=g).softmax(0)
    vertices = vertex_matrices(VERTEX_NAMES)
    labelled = write_explorer(
        tmp_path / "labelled.html", [embedded("ex", np.zeros((6, 8, 3), np.uint8), probs, labels)],
        vertices, VERTEX_NAMES,
    )  # fmt: skip
    bare = write_explorer(
        tmp_path / "bare.html", [embedded("ex", np.zeros((6, 8, 3), np.uint8), probs)],
        vertices, VERTEX_NAMES,
    )  # fmt: skip
    steps = [(page, "w=1,0,0", None), (labelled, "w=1,0,0", None),
             (labelled, "w=1,0,0", None, "car"), (bare, "w=1,0,0", None)]  # fmt: skip
    shown = page_states(page, steps)
    for step in shown:
        assert all(name in step["legend"] for name in (*CLASS_NAMES, "deferred"))
        assert '"ms"' not in step["visible"] and "labels_sha256" not in step["visible"]
        assert step["state"]["examples"]  # the state stays readable for scripts
    assert [step["choice"] for step in shown] == ["block", "block", "block", "none"]
    assert "of person over the 1 embedded" in shown[1]["metrics"]
    assert "of car over the 1 embedded" in shown[2]["metrics"]
    precision = [re.findall(r"image(–|[01]\.\d{4})", step["metrics"]) for step in shown[1:3]]
    d, t = np.asarray(reference_labels(probs, [1, 0, 0])), labels  # the reference's numbers
    for cls, found in zip((11, 13), precision, strict=True):
        tp = np.sum((d == cls) & (t == cls))
        expected = f"{tp / np.sum(d == cls):.4f}" if np.sum(d == cls) else "–"
        assert found[0] == expected, (cls, found)
    assert shown[3]["metrics"] == ""
