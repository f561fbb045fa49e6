"""The explorer page in a real browser (headless Chromium): its masks at any point of the
triangle equal the float64 reference on the embedded float16 probabilities, pixel for pixel."""

from __future__ import annotations

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
from explorer_page import embedded_probs

from costseg.costs import barycentric_grid, mix_costs
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


def browser(page: Path, fragment: str, *extra: str) -> str:
    """Chromium's DOM of ``page#fragment`` once its scripts ran (or its output with ``extra``)."""
    args = [CHROMIUM, "--headless", "--no-sandbox", "--disable-gpu", "--virtual-time-budget=30000"]
    out = subprocess.run(
        [*args, *(extra or ("--dump-dom",)), f"{page.as_uri()}#{fragment}"],
        capture_output=True,
        text=True,
        timeout=180,
    )
    return out.stdout


def page_state(page: Path, weights: str, dom: str | None = None) -> dict:
    """The JSON of the page's ``costseg-state`` element at ``#w=weights`` (from ``dom``)."""
    dom = dom or browser(page, f"w={weights}")
    found = re.search(r'<pre id="costseg-state"[^>]*>(.*?)</pre>', dom)
    assert found, "the page holds no costseg-state element"
    return json.loads(html.unescape(found.group(1)))


def reference_sha(probs: torch.Tensor, weights: list[float]) -> str:
    vertices = vertex_matrices(VERTEX_NAMES)
    w = torch.tensor([weights], dtype=torch.float64)
    mixed = mix_costs(vertices, w)[0]
    # the page mixes (w0*C0 + w1*C1) + w2*C2; mix_costs must round the same way
    assert torch.equal(
        mixed, (w[0, 0] * vertices[0] + w[0, 1] * vertices[1]) + w[0, 2] * vertices[2]
    )
    labels = decide_reference(probs[None], mixed)[0]
    return hashlib.sha256(labels.numpy().astype(np.uint8).tobytes()).hexdigest()


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
@pytest.mark.parametrize("weights", WEIGHTS)
def test_page_masks_equal_the_reference(page, weights):
    state = page_state(page, weights)
    assert state["w"] == [float(x) for x in weights.split(",")]
    probs = embedded_probs(page)
    assert [e["name"] for e in state["examples"]] == list(probs)
    for example in state["examples"]:
        p = probs[example["name"]]
        assert (example["height"], example["width"]) == tuple(p.shape[1:])
        assert example["labels_sha256"] == reference_sha(p, state["w"]), example["name"]


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
    shown = {"0.5,0.5,0": "swept metrics", "0.3,0.3,0.4": "over the 2 embedded examples"}
    for weights, metrics in shown.items():  # a grid point, and between grid points
        dom = browser(page, f"w={weights}")
        assert metrics in dom
        state = page_state(page, weights, dom)
        for example in state["examples"]:
            p = probs[example["name"]]
            assert example["labels_sha256"] == reference_sha(p, state["w"]), example["name"]
