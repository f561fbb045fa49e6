"""Shifted test sets (docs/definitions.md §17): identity at severity 0, deterministic, pixels not
labels, ImageNet-C's formulas against independent references, and evaluate.py --shift."""

from __future__ import annotations

import colorsys
import json

import numpy as np
import pytest
import torch

from costseg.checkpoints import find_checkpoint
from costseg.cli import evaluate_main
from costseg.data.shift import CORRUPTIONS, Shift, ShiftedDataset, parse_shift, shift_image
from costseg.data.toy import StreetScenes

SCENES = StreetScenes("val", 3, (64, 128))


def scene() -> np.ndarray:
    return SCENES[0][0].permute(1, 2, 0).numpy().copy()


def test_severity_zero_is_the_image_itself_bit_for_bit():
    for name in CORRUPTIONS:
        shifted = ShiftedDataset(SCENES, Shift(name, 0))
        for i in range(len(SCENES)):
            assert torch.equal(shifted[i][0], SCENES[i][0]), name


def test_an_onset_leaves_the_images_before_it_clean_and_shifts_the_rest_as_without_one():
    everywhere = ShiftedDataset(SCENES, Shift("fog", 3), seed=4)
    later = ShiftedDataset(SCENES, Shift("fog", 3), seed=4, onset=2)
    for i in range(2):
        assert torch.equal(later[i][0], SCENES[i][0])
    assert torch.equal(later[2][0], everywhere[2][0]) and not torch.equal(later[2][0], SCENES[2][0])


@pytest.mark.parametrize("name", sorted(CORRUPTIONS))
def test_each_corruption_changes_pixels_not_labels_the_same_way_for_a_seed(name):
    image = scene()
    a, b = shift_image(image, Shift(name, 3), seed=1), shift_image(image, Shift(name, 3), seed=1)
    assert a.dtype == np.uint8 and a.shape == image.shape
    assert np.array_equal(a, b)
    assert (a != image).any(), name
    shifted = ShiftedDataset(SCENES, Shift(name, 3), seed=4)
    items = [shifted[i] for i in (2, 0, 1)]  # any order: each image has its own seed
    again = ShiftedDataset(SCENES, Shift(name, 3), seed=4)
    for i, (img, label) in zip((2, 0, 1), items, strict=True):
        assert torch.equal(img, again[i][0]) and torch.equal(label, SCENES[i][1])
    _, label, ids = shifted.with_instances(1)  # the instance path sees the shift too
    assert torch.equal(shifted.with_instances(1)[0], shifted[1][0])
    assert torch.equal(ids, SCENES.with_instances(1)[2]) and torch.equal(label, SCENES[1][1])


def test_a_random_corruption_differs_between_seeds_and_severities_grow():
    image = scene()
    noisy = [shift_image(image, Shift("gaussian_noise", s), seed=0).astype(float) for s in (1, 5)]
    assert not np.array_equal(
        shift_image(image, Shift("rain", 2), 0), shift_image(image, Shift("rain", 2), 1)
    )
    assert np.abs(noisy[1] - image).mean() > 2 * np.abs(noisy[0] - image).mean()


def test_gaussian_and_shot_noise_have_imagenet_c_s_spread():
    grey = np.full((256, 256, 3), 128, np.uint8)
    for severity, std in ((1, 0.08), (3, 0.18)):
        out = shift_image(grey, Shift("gaussian_noise", severity), seed=0) / 255.0
        assert np.std(out - 128 / 255) == pytest.approx(std, rel=0.05)
    # Poisson(x · c) / c at ImageNet-C's c = 60 photons: variance x / c
    out = shift_image(grey, Shift("shot_noise", 1), seed=0) / 255.0
    assert np.mean(out) == pytest.approx(128 / 255, abs=0.01)
    assert np.var(out) == pytest.approx((128 / 255) / 60, rel=0.1)


def test_brightness_raises_the_hsv_value_as_imagenet_c():
    image = np.array([[[200, 100, 50], [0, 0, 0], [10, 240, 120]]], np.uint8)
    out = shift_image(image, Shift("brightness", 2), seed=0)
    for pixel, got in zip(image[0], out[0], strict=True):
        h, s, v = colorsys.rgb_to_hsv(*(pixel / 255.0))
        want = np.array(colorsys.hsv_to_rgb(h, s, min(v + 0.2, 1.0))) * 255
        assert np.abs(got - want).max() <= 0.5 + 1e-9, (pixel, got, want)


def test_contrast_pulls_each_channel_to_its_mean():
    image = np.array([[[0, 100, 200], [100, 100, 0]]], np.uint8)
    out = shift_image(image, Shift("contrast", 1), seed=0)  # c = 0.4
    means = image.reshape(-1, 3).mean(0)
    want = np.rint((image - means) * 0.4 + means)
    assert np.array_equal(out, want.astype(np.uint8))


def test_bad_shifts_are_refused():
    assert parse_shift("fog:5") == Shift("fog", 5)
    for bad, needle in (
        ("smog:2", "unknown shift"),
        ("fog:6", "severity 0 to 5"),
        ("fog", "NAME:SEVERITY"),
    ):
        with pytest.raises(ValueError, match=needle):
            parse_shift(bad)


def _evaluate(ckpt, out, *extra):
    evaluate_main(
        ["--ckpt_path", str(ckpt), "--cost", "robotistic", "altruistic", "--classes", "person",
         "--limit", "2", "--num_examples", "0", "--no-progress", "--output_dir", str(out), *extra]
    )  # fmt: skip
    return out


def test_evaluate_under_several_shifts(tiny_run, tmp_path, capsys):
    """One complete evaluation of the clean images and one per shift; severity 0 reports what
    the clean images give; shifts.md in table.md's units (ECE as the terminal's fraction)."""
    ckpt = find_checkpoint(None, runs_dir=tiny_run[2])
    out = _evaluate(ckpt, tmp_path / "shifted", "--shift", "fog:0", "night:4")
    assert not (out / "INCOMPLETE").exists() and not (out / "clean").exists()  # fog:0 is
    same = json.loads((out / "fog_0" / "results.json").read_text())
    out = _evaluate(ckpt, tmp_path / "with_clean", "--shift", "night:4", "fog:2")
    clean = json.loads((out / "clean" / "results.json").read_text())
    dark = json.loads((out / "night_4" / "results.json").read_text())
    assert same["rows"] == clean["rows"] and same["miou"] == clean["miou"]
    assert clean["options"]["shift"] == [] and "seen through" not in clean["probabilities"]
    assert dark["miou"] != clean["miou"] and dark["options"]["shift"] == ["night:4"]
    assert "seen through night:4" in dark["probabilities"]
    summary = json.loads((out / "shifts.json").read_text())
    assert [(r["shift"], r["rule"]) for r in summary["rows"]] == [
        ("clean", "robotistic"), ("clean", "altruistic"),
        ("night:4", "robotistic"), ("night:4", "altruistic"),
        ("fog:2", "robotistic"), ("fog:2", "altruistic"),
    ]  # fmt: skip
    assert summary["rows"][2]["miou"] == dark["miou"]["robotistic"]
    table = (out / "shifts.md").read_text()
    row = next(line for line in table.splitlines() if line.startswith("| clean | robotistic |"))
    cells = [c.strip() for c in row.strip("|").split("|")]
    assert cells[2] == f"{100 * clean['miou']['robotistic']:.2f}"  # in %, as table.md
    assert cells[-2:] == [f"{clean['ece']['raw']:.4g}", f"{clean['nll']['raw']:.4g}"]


def test_shift_refusals(tiny_run, tmp_path, capsys):
    ckpt = str(find_checkpoint(None, runs_dir=tiny_run[2]))
    for args, needle in (
        (["--ckpt_path", ckpt, "--shift", "smog:1"], "unknown shift 'smog'"),
        (["--ckpt_path", ckpt, "--shift", "fog:1", "fog:1"], "names a shift twice"),
        (
            ["--probs", str(tmp_path), "--data_root", str(tmp_path), "--shift", "fog:1"],
            "--shift needs a network",
        ),
    ):
        with pytest.raises(SystemExit) as exit_:
            evaluate_main([*args, "--no-progress", "--output_dir", str(tmp_path / "out")])
        assert exit_.value.code == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and needle in err[0], err
