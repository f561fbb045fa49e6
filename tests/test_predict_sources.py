"""predict.py with other sources and the explorer, end to end: the saved probabilities equal a
forward pass written out in the test, and the labels the float64 reference on them."""

from __future__ import annotations

import json
import zlib
from pathlib import Path

import numpy as np
import pytest
import torch
from explorer_page import embedded_probs, page_json
from PIL import Image

from costseg.classes import LABEL_ID_TO_TRAIN_ID
from costseg.cli import predict_main
from costseg.costs import load_cost
from costseg.decision import decide_reference

IMAGENET = torch.tensor([0.485, 0.456, 0.406]), torch.tensor([0.229, 0.224, 0.225])
"""The mean and std of the ImageNet statistics both DeepLabs were trained with."""
SIZES = {"a": (48, 80), "b": (40, 64), "c": (32, 48)}


@pytest.fixture(scope="module")
def checkpoint(tiny_run) -> Path:
    return next(Path(tiny_run[2]).glob("**/last.ckpt"))


@pytest.fixture(scope="module")
def images(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("images")
    for k, (stem, (h, w)) in enumerate(SIZES.items()):
        rng = np.random.default_rng(k)
        Image.fromarray(rng.integers(0, 256, (h, w, 3), dtype=np.uint8)).save(
            folder / f"{stem}.png"
        )
    return folder


def _image(folder: Path, stem: str) -> torch.Tensor:
    """(1, 3, H, W) float the network sees: ImageNet-normalised RGB in [0, 1]."""
    x = torch.from_numpy(np.array(Image.open(folder / f"{stem}.png"))).permute(2, 0, 1)
    return ((x.double() / 255 - IMAGENET[0][:, None, None]) / IMAGENET[1][:, None, None])[None]


def _saved(out: Path, stem: str) -> torch.Tensor:
    probs = np.load(out / "probs" / f"{stem}.npz")["probs"]
    assert probs.dtype == np.float16
    return torch.from_numpy(probs).float()


def _labels_are_the_reference(out: Path, rules: list[str], stems) -> None:
    for stem in stems:
        probs = _saved(out, stem)[None]
        for rule in rules:
            ids = np.asarray(Image.open(out / "labels" / rule / f"{stem}.png"))
            expected = decide_reference(probs, load_cost(rule))[0].numpy()
            np.testing.assert_array_equal(LABEL_ID_TO_TRAIN_ID[ids], expected, f"{stem} {rule}")


def test_network_vainf_is_the_vainf_forward(vainf, images, tmp_path):
    net, path = vainf
    out = tmp_path / "out"
    rules = ["robotistic", "egoistic"]
    predict_main(["--input", str(images), "--network", f"vainf:{path}", "--cost", *rules,
                  "--save-probs", "--output_dir", str(out), "--no-progress"])  # fmt: skip
    with torch.no_grad():
        for stem in SIZES:
            expected = net(_image(images, stem).float()).double().softmax(1)[0]
            torch.testing.assert_close(_saved(out, stem).double(), expected, atol=1e-3, rtol=0)
    _labels_are_the_reference(out, rules, SIZES)
    assert "vainf" in json.dumps(json.loads((out / "counts.json").read_text())["source"])


def test_mc_dropout_is_the_mean_of_seeded_dropout_passes(checkpoint, images, tmp_path):
    """§12: N passes, dropout active and batch norm in eval mode, seeded by CRC-32 of the seed
    and the image's name; the mean softmax."""
    from costseg.training.module import SegmentationModule

    out, passes, seed = tmp_path / "out", 3, 7
    predict_main(["--input", str(images), "--ckpt_path", str(checkpoint), "--mc_dropout",
                  str(passes), "--seed", str(seed), "--cost", "egoistic", "--save-probs",
                  "--output_dir", str(out), "--no-progress"])  # fmt: skip
    module = SegmentationModule.load_from_checkpoint(checkpoint, map_location="cpu").eval()
    dropout = [m for m in module.modules() if isinstance(m, torch.nn.Dropout)]
    assert dropout and all(not m.training for m in module.modules())
    with torch.no_grad():
        for stem in SIZES:
            x = torch.from_numpy(np.array(Image.open(images / f"{stem}.png")))
            x = x.permute(2, 0, 1)[None]
            plain = module(x).double().softmax(1)[0]
            for m in dropout:
                m.train()
            torch.manual_seed(zlib.crc32(f"{seed}\n{stem}".encode()))
            passes_ = [module(x).double().softmax(1)[0] for _ in range(passes)]
            for m in dropout:
                m.eval()
            expected = sum(passes_) / passes
            saved = _saved(out, stem).double()
            torch.testing.assert_close(saved, expected, atol=1e-3, rtol=0)
            assert (saved - plain).abs().max() > 1e-2  # the dropout shows
    _labels_are_the_reference(out, ["egoistic"], SIZES)
    source = json.loads((out / "counts.json").read_text())["source"]
    assert source["mc_dropout"] == {"passes": passes, "seed": seed}


def test_explorer_embeds_the_saved_probabilities_and_the_scaled_vertices(
    checkpoint, images, tmp_path
):
    out = tmp_path / "out"
    rules = ["robotistic", "egoistic"]
    predict_main(["--input", str(images), "--ckpt_path", str(checkpoint), "--cost", *rules,
                  "--explorer", "--num_examples", "2", "--vertex_scaling", "mean",
                  "--save-probs", "--output_dir", str(out), "--no-progress"])  # fmt: skip
    page = out / "explorer.html"
    data, probs = page_json(page), embedded_probs(page)
    assert list(probs) == ["a", "b"]  # the first --num_examples images
    for stem, p in probs.items():
        assert torch.equal(p.float(), _saved(out, stem))
    names = ["robotistic", "altruistic", "egoistic"]
    assert data["vertexNames"] == names
    vertices = torch.tensor(data["vertices"], dtype=torch.float64).reshape(3, 19, 19)
    for name, vertex in zip(names, vertices, strict=True):
        cost = load_cost(name).double()
        off = [cost[i, j].item() for i in range(19) for j in range(19) if i != j]
        torch.testing.assert_close(vertex, cost / (sum(off) / len(off)), rtol=1e-12, atol=0)
    assert {p["label"]: p["w"] for p in data["named"]} == {
        "robotistic": [1.0, 0.0, 0.0], "egoistic": [0.0, 0.0, 1.0],
    }  # fmt: skip
    _labels_are_the_reference(out, rules, SIZES)
    for stem, p in probs.items():  # the page's corners decide as the labels written...
        for rule, vertex in zip(names, vertices, strict=True):
            if rule in rules:
                ids = np.asarray(Image.open(out / "labels" / rule / f"{stem}.png"))
                want = torch.from_numpy(LABEL_ID_TO_TRAIN_ID[ids]).long()
                got = decide_reference(p.float()[None], vertex)[0]
                # ...up to near ties: the rescaled matrix rounds differently; where the two
                # differ, both classes cost the same to 1e-12 under the matrix of the labels.
                expected = torch.einsum("jhw,ij->ihw", p.double(), load_cost(rule).double())
                gap = (expected.gather(0, got[None]) - expected.gather(0, want[None])).abs()
                assert (gap[0][got != want] <= 1e-12 * expected.max()).all(), f"{stem} {rule}"
                assert (got == want).float().mean() > 0.999
