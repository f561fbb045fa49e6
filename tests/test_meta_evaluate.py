"""`evaluate.py --meta --save-segments --fuse` end to end on the tiny checkpoint: the segments
tile every labelled pixel, results.json's scores equal sklearn's on the CSV's columns, the saved
models give the same predictions, the fused rules are reported, and the refusals."""

from __future__ import annotations

import contextlib
import csv
import io
import json

import numpy as np
import pytest
from matplotlib import colormaps
from PIL import Image
from scipy import ndimage
from sklearn.metrics import r2_score, roc_auc_score
from test_cli_errors import _one_line

from costseg.checkpoints import find_checkpoint
from costseg.classes import CLASS_NAMES, IGNORE_INDEX, LABEL_ID_TO_TRAIN_ID
from costseg.cli import evaluate_main, predict_main
from costseg.data.toy import StreetScenes
from costseg.meta.models import MODELS, SHOWN_MODEL, load_models
from costseg.prediction.panels import TITLE
from costseg.report.uncertainty import IOU_COLOURS, NO_SEGMENT

RULES = ["robotistic", "ml"]
META = ["--meta", "--meta_split", "train", "--meta_images", "6", "--save-segments"]
FUSE = ["--fuse", "ml", "--fuse_tau", "0", "0.5", "1"]


@pytest.fixture(scope="module")
def ckpt(tiny_run) -> str:
    return str(find_checkpoint(None, runs_dir=tiny_run[2]))


GUARANTEED_TARGET = [
    *("--target", "person:roi1:recall>=0.5", "--maximize", "person:roi1:precision"),
    *("--guarantee", "0.2"),
]


@pytest.fixture(scope="module")
def evaluated(ckpt, tmp_path_factory):
    out = tmp_path_factory.mktemp("meta") / "eval"
    args = ["--ckpt_path", ckpt, "--cost", *RULES, *META, *FUSE, "--output_dir", str(out)]
    with contextlib.redirect_stdout(io.StringIO()) as printed:
        results = evaluate_main([*args, "--num_examples", "1", "--no-progress"])
    (out / "stdout.txt").write_text(printed.getvalue())  # the terminal, beside the outputs
    return out, results


def _csv(path) -> list[dict]:
    with open(path) as f:
        return list(csv.DictReader(f))


def test_the_segments_tile_every_labelled_pixel(evaluated, tiny_run) -> None:
    out, _ = evaluated
    scenes = StreetScenes("val", 3, (64, 128), seed=0)
    for rule in RULES:
        rows = _csv(out / "segments" / f"{rule}.csv")
        for stem in sorted({r["image"] for r in rows}):
            mine = [r for r in rows if r["image"] == stem]
            labels = scenes[int(stem.split("_")[-1])][1].numpy()
            assert sum(int(r["S"]) for r in mine) == (labels != IGNORE_INDEX).sum()
            assert [int(r["segment"]) for r in mine] == list(range(1, len(mine) + 1))
            for r in mine:
                assert int(r["S_in"]) + int(r["S_bd"]) == int(r["S"])
                assert (float(r["iou"]) == 0) == (r["iou0"] == "1")


def test_the_scores_equal_sklearn_s_on_the_csv_and_the_saved_models(evaluated) -> None:
    out, _ = evaluated
    record = json.loads((out / "results.json").read_text())["meta"]
    models = load_models(out / "meta" / "models.joblib")
    for rule in RULES:
        rows = _csv(out / "segments" / f"{rule}.csv")
        columns = {k: np.array([float(r[k]) for r in rows]) for k in rows[0] if k != "image"}
        false, iou = columns["iou0"].astype(int), columns["iou"]
        for model, scores in record["scores"][rule].items():
            if scores["auroc"] is not None:
                assert scores["auroc"] == pytest.approx(
                    roc_auc_score(false, columns[f"{model}_false"])
                )
            if scores["r2"] is not None:
                assert scores["r2"] == pytest.approx(r2_score(iou, columns[f"{model}_iou"]))
            predicted = models[rule].predicted_iou(model, columns)
            np.testing.assert_allclose(predicted, columns[f"{model}_iou"], rtol=1e-12)
        assert record["fitted_on"]["images"] == 6


def test_the_terminal_gives_each_rule_s_auroc_and_r2(evaluated) -> None:
    out, _ = evaluated
    scores = json.loads((out / "results.json").read_text())["meta"]["scores"]
    printed = (out / "stdout.txt").read_text().splitlines()
    header = printed.index(next(line for line in printed if line.split()[:2] == ["rule", "AUROC"]))
    assert printed[header].split() == ["rule"] + [
        word
        for s in ("AUROC", "R²")
        for m in ("logistic", "boosting", "entropy")
        for word in (s, m)
    ]
    for rule, line in zip(RULES, printed[header + 2 : header + 2 + len(RULES)], strict=True):
        values = [scores[rule][m][s] for s in ("auroc", "r2") for m in MODELS]
        assert line.split() == [rule, *(f"{v:.4g}" for v in values)]


def test_the_fused_rules_are_reported_like_any_rule(evaluated) -> None:
    out, results = evaluated
    rows = _csv(out / "fusion.csv")
    assert {r["matrix"] for r in rows} == {"ml+meta@0", "ml+meta@0.5", "ml+meta@1"}
    # the example masks: robotistic, ml, then the fused maps, which differ from the base
    # (robotistic) only where they take ml's person pixels
    base, ml, *fused = results.examples[0].preds.numpy()
    assert len(fused) == 3
    person = CLASS_NAMES.index("person")
    for labels in fused:
        changed = labels != base
        assert (labels[changed] == ml[changed]).all() and (ml[changed] == person).all()
    assert {"fp_segments", "missed_instances", "precision", "recall"} <= rows[0].keys()
    for name in ("meta_iou_scatter", "meta_feature_importance", "meta_segments_0_ml"):
        assert (out / "figures" / f"{name}.png").is_file(), name
    assert "## Meta classification of segments" in (out / "table.md").read_text()


@pytest.mark.parametrize(
    "extra, words",
    [
        (["--meta", "--meta_split", "val"], ["--meta_split val overlaps"]),
        (["--meta_split", "train"], ["--meta_split goes with --meta or --fuse"]),
        (
            ["--meta_images", "5", "--meta_split", "train"],
            ["--meta_split, --meta_images go with --meta or --fuse"],
        ),
        (["--fuse_tau", "0.3"], ["--fuse_tau goes with --fuse"]),
        (["--fuse", "ml", "--fuse_tau", "1.5"], ["--fuse_tau", "[0, 1]"]),
        (["--fuse", "ml", "--fuse_base", "unicorn"], ["unknown cost 'unicorn'"]),
        ([*FUSE, *GUARANTEED_TARGET], ["give --meta_split"]),
    ],
)
def test_meta_options_are_refused_in_one_line(ckpt, tmp_path, capsys, extra, words) -> None:
    args = ["--ckpt_path", ckpt, "--output_dir", str(tmp_path / "x"), *extra]
    _one_line(evaluate_main, args, capsys, *words)


def test_predict_draws_the_saved_models_predicted_iou(evaluated, ckpt, tmp_path) -> None:
    """predict.py --meta_models on an evaluated image: below each rule's difference view, every
    pixel of the panel's IoU tile has the colour of its segment's predicted IoU in the rule's
    segments CSV (the segments found again by scipy's 8-connected labelling, numbered by first
    pixel). The image is one without ignored pixels, whose segments evaluate.py and predict.py
    cut alike."""
    out, _ = evaluated
    rows = {rule: _csv(out / "segments" / f"{rule}.csv") for rule in RULES}
    scenes = StreetScenes("val", 3, (64, 128), seed=0)
    index = next(i for i in range(len(scenes)) if (scenes[i][1] != IGNORE_INDEX).all())
    image = scenes[index][0]
    stem = next(r["image"] for r in rows["ml"] if int(r["image"].split("_")[-1]) == index)
    folder = tmp_path / "images"
    folder.mkdir()
    Image.fromarray(image.permute(1, 2, 0).numpy()).save(folder / f"{stem}.png")
    predicted = tmp_path / "predicted"
    models = str(out / "meta" / "models.joblib")
    predict_main(["--input", str(folder), "--ckpt_path", ckpt, "--cost", *RULES, "--no-progress",
                  "--meta_models", models, "--output_dir", str(predicted)])  # fmt: skip
    panel = np.asarray(Image.open(predicted / "panels" / f"{stem}.png"))
    palette = colormaps[IOU_COLOURS](np.linspace(0, 1, 256))[:, :3]
    h, w = 96, 192  # the tiles of a 64 x 128 image (1.5 x)
    for k, rule in enumerate(RULES):
        ids = LABEL_ID_TO_TRAIN_ID[
            np.asarray(Image.open(predicted / "labels" / rule / f"{stem}.png"))
        ]
        segments = _segments(ids)
        iou = {int(r["segment"]): float(r[f"{SHOWN_MODEL}_iou"]) for r in rows[rule]
               if r["image"] == stem}  # fmt: skip
        assert len(iou) == segments.max()
        lookup = np.array([np.nan] + [iou[i] for i in range(1, len(iou) + 1)])
        values = lookup[segments[np.arange(h)[:, None] * 64 // h, np.arange(w) * 128 // w]]
        expected = np.where(
            np.isnan(values)[..., None],
            NO_SEGMENT,
            np.round(255 * palette[np.round(255 * np.nan_to_num(values)).astype(int)]),
        )
        top = 2 * (h + TITLE) + TITLE
        tile = panel[top : top + h, (k + 1) * w : (k + 2) * w]
        assert np.abs(tile.astype(int) - expected).max() <= 3, rule


def _segments(labels: np.ndarray) -> np.ndarray:
    """Segment ids by scipy: 8-connected components of each label (255: none), numbered in
    row-major order of their first pixel."""
    ids, first = np.zeros(labels.shape, np.int64), []
    for c in np.unique(labels[labels != IGNORE_INDEX]):
        components, n = ndimage.label(labels == c, structure=np.ones((3, 3)))
        for j in range(1, n + 1):
            mask = components == j
            first.append((int(np.flatnonzero(mask.ravel())[0]), mask))
    for i, (_, mask) in enumerate(sorted(first, key=lambda f: f[0]), start=1):
        ids[mask] = i
    return ids


def test_predict_refuses_models_of_other_rules(evaluated, ckpt, tmp_path, capsys) -> None:
    out, _ = evaluated
    folder = tmp_path / "images"
    folder.mkdir()
    Image.fromarray(np.zeros((64, 128, 3), np.uint8)).save(folder / "black.png")
    args = ["--input", str(folder), "--ckpt_path", ckpt, "--cost", "egoistic", "--output_dir",
            str(tmp_path / "p"), "--meta_models", str(out / "meta" / "models.joblib")]  # fmt: skip
    _one_line(predict_main, args, capsys, "holds no gradient_boosting models of egoistic")
    (out / "meta" / "copy.joblib").write_bytes(
        b"not the file" + (out / "meta" / "models.joblib").read_bytes()
    )
    (out / "meta" / "copy.json").write_text((out / "meta" / "models.json").read_text())
    args[-1] = str(out / "meta" / "copy.joblib")
    _one_line(predict_main, args, capsys, "is not the file costseg wrote")
    (out / "meta" / "copy.json").unlink()
    _one_line(predict_main, args, capsys, "copy.json not found: evaluate.py writes it beside")
    args[-1] = str(out / "meta")
    _one_line(predict_main, args, capsys, "is a folder; give meta/models.joblib")
