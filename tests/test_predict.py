"""predict.py on a user's own images and videos: labels equal the float64 reference on the
saved probabilities, videos keep their frame count and rate, and bad inputs end in one line."""

from __future__ import annotations

import csv
import json
import sys
from fractions import Fraction
from pathlib import Path

import numpy as np
import pytest
import torch
from interrupts import ROOT, interrupt_when, start_job
from PIL import Image
from scipy import ndimage

from costseg.classes import LABEL_ID_TO_TRAIN_ID, class_index
from costseg.cli import CLASS_PREFIX, predict_main
from costseg.costs import load_cost
from costseg.data.priors import resize_priors
from costseg.decision import decide_reference
from costseg.networks import load_costseg_checkpoint
from costseg.prediction.inputs import find_inputs
from costseg.report.outputs import INCOMPLETE

RULES = ["robotistic", "altruistic", "egoistic", "ml"]


@pytest.fixture(scope="module")
def checkpoint(tiny_run) -> Path:
    return next(Path(tiny_run[2]).glob("**/last.ckpt"))


def _picture(h: int, w: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    base = np.linspace(0, 255, w, dtype=np.float32)[None, :, None] * np.ones((h, 1, 3))
    return (base + rng.normal(0, 30, (h, w, 3))).clip(0, 255).astype(np.uint8)


@pytest.fixture
def images(tmp_path) -> Path:
    """Two PNGs of different sizes and a JPEG stored sideways (EXIF orientation 6)."""
    folder = tmp_path / "images"
    folder.mkdir()
    Image.fromarray(_picture(48, 80, 0)).save(folder / "wide.png")
    Image.fromarray(_picture(37, 53, 1)).convert("L").save(folder / "odd.png")
    exif = Image.Exif()
    exif[0x0112] = 6  # rotate 90° clockwise to view
    Image.fromarray(_picture(40, 64, 2)).save(folder / "photo.jpg", exif=exif, quality=90)
    return folder


def test_labels_equal_the_reference_on_the_saved_probabilities(checkpoint, images, tmp_path):
    out = tmp_path / "out"
    predict_main(["--input", str(images), "--ckpt_path", str(checkpoint), "--output_dir",
                  str(out), "--save-probs", "--cost", *RULES, "--no-progress"])  # fmt: skip
    priors = load_costseg_checkpoint(checkpoint).priors
    sizes = {"wide": (48, 80), "odd": (37, 53), "photo": (64, 40)}  # the JPEG turned upright
    rows = list(csv.DictReader((out / "counts.csv").open()))
    for stem, size in sizes.items():
        probs = torch.from_numpy(np.load(out / "probs" / f"{stem}.npz")["probs"])
        assert probs.dtype == torch.float16 and tuple(probs.shape) == (19, *size)
        assert (out / "panels" / f"{stem}.png").is_file()
        for rule in RULES:
            cost, pi = (
                (None, resize_priors(priors, size)) if rule == "ml" else (load_cost(rule), None)
            )
            expected = decide_reference(probs[None].float(), cost, pi)[0].numpy()
            ids = np.asarray(Image.open(out / "labels" / rule / f"{stem}.png"))
            np.testing.assert_array_equal(LABEL_ID_TO_TRAIN_ID[ids], expected, f"{stem} {rule}")
            color = np.asarray(Image.open(out / "color" / rule / f"{stem}.png"))
            assert color.shape == (*size, 3)
            mine = {r["class"]: r for r in rows if r["image"] == stem and r["rule"] == rule
                    and r["roi"] == "image"}  # fmt: skip
            for cls in ("building", "sky", "person"):
                mask = expected == class_index(cls)
                segments = ndimage.label(mask, structure=np.ones((3, 3)))[1]
                assert int(mine[cls]["pixels"]) == mask.sum()
                assert int(mine[cls]["segments"]) == segments
    counts = json.loads((out / "counts.json").read_text())
    assert counts["rois"] == ["image", "street", "sidewalk", "building", "sky"]


def _cityscapes_layout(root: Path) -> Path:
    """``leftImg8bit/val/<city>/`` with the same file name in two cities (different pictures)."""
    for seed, city in enumerate(("aachen", "bonn")):
        (root / city).mkdir(parents=True)
        Image.fromarray(_picture(24, 40, seed)).save(root / city / "x_leftImg8bit.png")
    Image.fromarray(_picture(24, 40, 2)).save(root / "bonn" / "y_leftImg8bit.png")
    return root


def test_inputs_are_named_by_their_path_below_the_common_folder(tmp_path):
    val = _cityscapes_layout(tmp_path / "leftImg8bit" / "val")
    Image.fromarray(_picture(24, 40, 3)).save(extra := tmp_path / "x_leftImg8bit.png")
    given = [val, extra, val / "bonn" / "y_leftImg8bit.png"]
    names = {i.path: i.name for i in find_inputs(given).items}
    assert names == {
        val / "aachen" / "x_leftImg8bit.png": "leftImg8bit/val/aachen/x_leftImg8bit",
        val / "bonn" / "x_leftImg8bit.png": "leftImg8bit/val/bonn/x_leftImg8bit",
        val / "bonn" / "y_leftImg8bit.png": "leftImg8bit/val/bonn/y_leftImg8bit",  # read once
        extra: "x_leftImg8bit",
    }
    assert [i.name for i in find_inputs([val]).items] == [
        "aachen/x_leftImg8bit", "bonn/x_leftImg8bit", "bonn/y_leftImg8bit"]  # fmt: skip


def test_a_cityscapes_folder_keeps_its_layout(checkpoint, tmp_path, capsys):
    val = _cityscapes_layout(tmp_path / "val")
    out, run = tmp_path / "out", ["--ckpt_path", str(checkpoint), "--no-progress", "--cost", "ml"]
    predict_main(["--input", str(val), "--output_dir", str(out), *run])
    alone = tmp_path / "alone"  # the reference: bonn's x in a run of its own
    predict_main(["--input", str(val / "bonn" / "x_leftImg8bit.png"), "--output_dir", str(alone),
                  *run])  # fmt: skip
    for kind in ("labels/ml", "color/ml", "panels"):
        mine = np.asarray(Image.open(out / kind / "bonn" / "x_leftImg8bit.png"))
        reference = np.asarray(Image.open(alone / kind / "x_leftImg8bit.png"))
        np.testing.assert_array_equal(mine, reference, kind)
    aachen = np.asarray(Image.open(out / "panels" / "aachen" / "x_leftImg8bit.png"))
    assert (aachen != reference).any()  # the other x: its own picture, not overwritten
    counts = json.loads((out / "counts.json").read_text())
    assert sorted(counts["images"]) == ["aachen/x_leftImg8bit", "bonn/x_leftImg8bit",
                                        "bonn/y_leftImg8bit"]  # fmt: skip
    capsys.readouterr()
    with pytest.raises(SystemExit):  # an earlier run's folder needs --overwrite ...
        predict_main(["--input", str(val / "bonn"), "--output_dir", str(out), *run])
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "pass --overwrite" in err[0], err
    predict_main(["--input", str(val / "bonn"), "--output_dir", str(out), "--overwrite", *run])
    counts = json.loads((out / "counts.json").read_text())  # ... which predict.py takes
    assert counts["input"] == [str(val / "bonn")]
    assert sorted(counts["images"]) == ["x_leftImg8bit", "y_leftImg8bit"]


def _write_video(path: Path, frames: int, rate: int) -> None:
    import av

    with av.open(str(path), "w") as container:
        stream = container.add_stream("mpeg4", rate=rate)
        stream.width, stream.height, stream.pix_fmt = 64, 48, "yuv420p"
        for i in range(frames):
            frame = av.VideoFrame.from_ndarray(_picture(48, 64, i), format="rgb24")
            container.mux(stream.encode(frame))
        container.mux(stream.encode(None))


def _frames_and_rate(path: Path) -> tuple[int, Fraction]:
    import av

    with av.open(str(path)) as container:
        stream = container.streams.video[0]
        return sum(1 for _ in container.decode(stream)), Fraction(stream.average_rate)


def test_a_video_gives_videos_of_the_same_frame_count_and_rate(checkpoint, tmp_path, capsys):
    pytest.importorskip("av")
    video, out = tmp_path / "clip.mp4", tmp_path / "out"
    _write_video(video, 6, 12)
    Image.fromarray(_picture(48, 64, 0)).save(image := tmp_path / "still.png")
    predict_main(["--input", str(video), str(image), "--ckpt_path", str(checkpoint),
                  "--output_dir", str(out)])  # fmt: skip
    err = capsys.readouterr().err
    assert "predict clip: 6/6 (100%)" in err and "predict: 1/1 (100%)" in err  # no terminal
    for name in ("clip_panels", "clip_robotistic", "clip_altruistic", "clip_egoistic"):
        assert _frames_and_rate(out / f"{name}.mp4") == (6, Fraction(12)), name
    images = json.loads((out / "counts.json").read_text())["images"]
    assert sorted(images) == ["clip_000000", "clip_000001", "clip_000002", "clip_000003",
                              "clip_000004", "clip_000005", "still"]  # fmt: skip
    assert (out / "panels" / "still.png").is_file()


def _bad(tmp_path: Path, kind: str) -> Path:
    if kind == "text.png":
        (path := tmp_path / "notes.png").write_text("not an image")
    elif kind == "corrupt.mp4":
        (path := tmp_path / "broken.mp4").write_bytes(b"\x00\x00\x00\x18ftypmp42" + bytes(300))
    elif kind == "empty folder":
        (path := tmp_path / "empty").mkdir()
        (path / "sub").mkdir()  # a sub-folder without images either
    elif kind == "two images named alike":
        (path := tmp_path / "twice").mkdir()
        for name in ("a.png", "a.jpg"):
            Image.fromarray(_picture(8, 8, 0)).save(path / name)
    else:
        path = tmp_path / "missing.jpg"
    return path


@pytest.mark.parametrize(
    "kind", ["text.png", "corrupt.mp4", "empty folder", "two images named alike", "missing"]
)
def test_bad_inputs_end_in_one_line_before_the_network_loads(tmp_path, capsys, kind):
    path = _bad(tmp_path, kind)
    with pytest.raises(SystemExit) as exit_:  # a checkpoint that does not exist is never read
        predict_main(["--input", str(path), "--ckpt_path", str(tmp_path / "none.ckpt")])
    err = capsys.readouterr().err.strip().splitlines()
    assert exit_.value.code == 2 and len(err) == 1, err
    assert err[0].startswith("error: ") and str(path) in err[0], err
    assert not CLASS_PREFIX.match(err[0][7:]), err


def test_ctrl_c_ends_in_one_line_and_status_130(checkpoint, tmp_path):
    """A real predict.py interrupted while it writes: one line, 130, the folder unfinished."""
    folder, out = tmp_path / "images", tmp_path / "out"
    folder.mkdir()
    Image.fromarray(_picture(48, 80, 0)).save(first := folder / "000.png")
    for i in range(1, 400):  # far more than are written before the interrupt arrives
        (folder / f"{i:03d}.png").hardlink_to(first)
    command = [sys.executable, str(ROOT / "predict.py"), "--input", str(folder), "--ckpt_path",
               str(checkpoint), "--output_dir", str(out), "--no-progress"]  # fmt: skip
    job = start_job(command)
    _, err = interrupt_when(job, lambda: any((out / "panels").glob("*.png")))
    assert job.returncode == 130, err
    assert len(err.strip().splitlines()) == 1 and err.startswith("interrupted"), err
    assert 0 < len(list((out / "panels").glob("*.png"))) < 400
    assert (out / INCOMPLETE).is_file() and not (out / "counts.json").exists()
