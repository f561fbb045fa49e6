"""predict.py --defer C (docs/definitions.md §14): the label PNGs equal the float64 reference with
the defer row on the saved probabilities (255 where deferred), the colour PNGs and panels draw
deferred pixels in DEFERRED_COLOUR, the counts hold each rule's defer cost and deferred share,
and bad defer options end in one line."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest
import torch
from explorer_page import page_json
from PIL import Image

from costseg.classes import DEFERRED_COLOUR, LABEL_ID_TO_TRAIN_ID, PALETTE
from costseg.cli import predict_main
from costseg.costs import load_cost, symmetric_cost, with_defer
from costseg.data.priors import resize_priors
from costseg.decision import decide_reference
from costseg.networks import load_costseg_checkpoint
from costseg.prediction.panels import ALPHA, TITLE, panel

DEFER = 0.6  # robotistic defers where max_k p_k < 0.4 (Chow); egoistic's costs reach 1000


@pytest.fixture(scope="module")
def checkpoint(tiny_run) -> Path:
    return next(Path(tiny_run[2]).glob("**/last.ckpt"))


@pytest.fixture
def images(tmp_path) -> Path:
    folder = tmp_path / "images"
    folder.mkdir()
    rng = np.random.default_rng(0)
    for name, (h, w) in {"a": (40, 72), "b": (29, 45)}.items():
        Image.fromarray(rng.integers(0, 256, (h, w, 3), dtype=np.uint8)).save(
            folder / f"{name}.png"
        )
    return folder


def _expected(rule: str, probs: torch.Tensor, priors: torch.Tensor) -> np.ndarray:
    """(H, W) decide_reference with the defer row DEFER (255: deferred), written in the test."""
    size = tuple(probs.shape[1:])
    cost = symmetric_cost(19) if rule == "ml" else load_cost(rule)
    pi = resize_priors(priors, size) if rule == "ml" else None
    return decide_reference(probs[None].float(), with_defer(cost, DEFER), pi)[0].numpy()


def test_labels_colours_and_counts_with_defer(checkpoint, images, tmp_path):
    out, rules = tmp_path / "out", ["robotistic", "egoistic", "ml"]
    predict_main(["--input", str(images), "--ckpt_path", str(checkpoint), "--output_dir", str(out),
                  "--save-probs", "--cost", *rules, "--defer", str(DEFER), "--explorer",
                  "--num_examples", "1", "--no-progress"])  # fmt: skip
    priors = load_costseg_checkpoint(checkpoint).priors
    rows = list(csv.DictReader((out / "counts.csv").open()))
    counts = json.loads((out / "counts.json").read_text())
    assert counts["defer"] == {"robotistic": DEFER, "egoistic": DEFER, "ml": DEFER}
    assert not (out / "labels" / "argmax").exists()  # argmax decides the panels' differences
    shares = []
    for stem in ("a", "b"):
        probs = torch.from_numpy(np.load(out / "probs" / f"{stem}.npz")["probs"])
        for rule in rules:
            expected = _expected(rule, probs, priors)
            ids = np.asarray(Image.open(out / "labels" / rule / f"{stem}.png"))
            np.testing.assert_array_equal(LABEL_ID_TO_TRAIN_ID[ids], expected, f"{stem} {rule}")
            deferred = expected == 255
            colour = np.asarray(Image.open(out / "color" / rule / f"{stem}.png"))
            assert (colour[deferred] == DEFERRED_COLOUR).all()
            assert (colour[~deferred] == PALETTE[expected[~deferred]]).all()
            by_hand = sum(int(expected[y, x] == 255) for y in range(expected.shape[0])
                          for x in range(expected.shape[1])) / expected.size  # fmt: skip
            mine = [r for r in rows if (r["image"], r["rule"], r["roi"]) == (stem, rule, "image")]
            assert len(mine) == 19 and {float(r["deferred"]) for r in mine} == {by_hand}
            record = counts["images"][stem][rule]
            assert record["deferred"][0] == by_hand
            assert (
                record["deferred_pixels"][0] == deferred.sum() == sum(record["deferred_pixels"][1:])
            )
            assert sum(p[0] for p in record["pixels"]) == expected.size - deferred.sum()
            shares.append((rule, by_hand))
    chow = [share for rule, share in shares if rule == "robotistic"]
    assert min(chow) > 0 and max(chow) < 1  # some pixels deferred, some not
    assert page_json(out / "explorer.html")["defer"] == DEFER


def _video(path: Path, frames: int) -> Path:
    import av

    rng = np.random.default_rng(1)
    with av.open(str(path), "w") as container:
        stream = container.add_stream("mpeg4", rate=10)
        stream.width, stream.height, stream.pix_fmt = 64, 48, "yuv420p"
        for _ in range(frames):
            image = rng.integers(0, 256, (48, 64, 3), dtype=np.uint8)
            container.mux(stream.encode(av.VideoFrame.from_ndarray(image, format="rgb24")))
        container.mux(stream.encode(None))
    return path


def test_a_video_with_a_cost_file_with_its_own_defer_row(checkpoint, tmp_path):
    pytest.importorskip("av")
    (cost := tmp_path / "cautious.yaml").write_text(
        "name: cautious\noff_diagonal: 1.0\ndefer: {default: 0.6, person: 0.3}\n"
    )
    video, out = _video(tmp_path / "clip.mp4", 2), tmp_path / "out"
    predict_main(["--input", str(video), "--ckpt_path", str(checkpoint), "--output_dir", str(out),
                  "--save-probs", "--cost", str(cost), "robotistic", "--no-progress"])  # fmt: skip
    assert (out / "clip_panels.mp4").is_file() and (out / "clip_cautious.mp4").is_file()
    counts = json.loads((out / "counts.json").read_text())
    row = [0.6] * 19
    row[11] = 0.3
    assert counts["defer"] == {"cautious": row, "robotistic": None}
    cautious = with_defer(symmetric_cost(19), torch.tensor(row))
    for stem in ("clip_000000", "clip_000001"):
        probs = torch.from_numpy(np.load(out / "probs" / f"{stem}.npz")["probs"])
        expected = decide_reference(probs[None].float(), cautious)[0].numpy()
        by_hand = sum(int(v == 255) for v in expected.ravel().tolist())
        assert counts["images"][stem]["cautious"]["deferred_pixels"][0] == by_hand > 0
        assert counts["images"][stem]["cautious"]["deferred"][0] == by_hand / expected.size
        assert counts["images"][stem]["robotistic"]["deferred"][0] == 0


@pytest.mark.parametrize("value", ["-1", "abc", "inf", "nan"])
def test_a_bad_defer_cost_ends_in_one_line(tmp_path, capsys, value):
    with pytest.raises(SystemExit) as exit_:
        predict_main(["--input", str(tmp_path), "--defer", value])
    err = capsys.readouterr().err.strip().splitlines()
    assert exit_.value.code == 2 and len(err) == 1, err
    assert "--defer" in err[0] and value in err[0], err


def test_defer_with_a_cost_file_that_defers_ends_in_one_line(tmp_path, capsys):
    (cost := tmp_path / "cautious.yaml").write_text("name: cautious\noff_diagonal: 1\ndefer: 0.2\n")
    with pytest.raises(SystemExit) as exit_:  # caught before the inputs and the network
        predict_main(["--input", str(tmp_path / "none.png"), "--cost", str(cost), "--defer", "0.3",
                      "--ckpt_path", str(tmp_path / "none.ckpt")])  # fmt: skip
    err = capsys.readouterr().err.strip().splitlines()
    assert exit_.value.code == 2 and len(err) == 1, err
    assert "defer row of its own" in err[0] and str(cost) in err[0], err


def test_panels_draw_deferred_pixels_and_state_the_share():
    image = np.zeros((8, 12, 3), np.uint8)
    maps = np.zeros((2, 8, 12), np.uint8)
    maps[0, :2] = 255  # rule 0 defers 2 rows of 8
    argmax = np.zeros((8, 12), np.uint8)
    plain = panel(image, ["a", "b"], maps, argmax)
    mine = panel(image, ["a", "b"], maps, argmax, ["0.3", None])
    assert mine.shape[0] - plain.shape[0] == 2 * (TITLE - 4)  # two-line titles over both rows
    scale = 192 // 12  # tiles are at least 192 pixels wide: 16 pixels per pixel
    top = 2 * TITLE - 4
    overlay = mine[top : top + 8 * scale, 192 : 2 * 192]  # rule 0's overlay
    white = round(ALPHA * 255)  # DEFERRED_COLOUR blended over a black image
    assert (overlay[: 2 * scale] == white).all()
    assert (overlay[2 * scale :] == np.round(ALPHA * PALETTE[0]).astype(np.uint8)).all()
    differ = mine[2 * top + 8 * scale : 2 * top + 16 * scale, 192 : 2 * 192]
    assert (differ[: 2 * scale] == DEFERRED_COLOUR).all()  # deferred differs from argmax
