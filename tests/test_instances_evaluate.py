"""`evaluate.py` on a Cityscapes tree written by scripts/toy_as_cityscapes.py: the instance
metrics of results.json against a brute-force loop over the written instance ids and the
predictions of ``--save-predictions``; Monte-Carlo dropout stated in every output."""

from __future__ import annotations

import importlib.util
import json
import sys
from pathlib import Path

import numpy as np
import pytest
from instance_reference import SIZES, reference_instances
from PIL import Image

from costseg.checkpoints import find_checkpoint
from costseg.classes import LABEL_ID_TO_TRAIN_ID, class_indices
from costseg.cli import evaluate_main
from costseg.data.cityscapes import INSTANCE_SUFFIX, LABEL_SUFFIX, CityscapesSegmentation
from costseg.data.prior_maps import PriorMaps
from costseg.data.priors import pixel_priors
from costseg.data.toy.dataset import StreetScenes

ROOT = Path(__file__).resolve().parents[1]
RULES = ("robotistic", "altruistic", "egoistic")
CLASSES = ("person", "car", "building")


def _toy_as_cityscapes():
    spec = importlib.util.spec_from_file_location(
        "toy_as_cityscapes", ROOT / "scripts" / "toy_as_cityscapes.py"
    )
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # where its options dataclass resolves its annotations
    spec.loader.exec_module(module)
    return module


def _edit(folder: Path) -> None:
    """A crowd region and a person cut by ignored pixels in the first validation image."""
    name = "toy_000000_000000"
    labels_path, ids_path = folder / f"{name}{LABEL_SUFFIX}", folder / f"{name}{INSTANCE_SUFFIX}"
    labels, ids = np.array(Image.open(labels_path)), np.array(Image.open(ids_path))
    labels[:5, :12], ids[:5, :12] = 24, 24  # crowd: person label id, no instance
    people = [v for v in np.unique(ids) if 24000 <= v < 25000]
    assert people, "the first validation scene should hold a person"
    cut = ids == people[0]
    labels[cut & (np.arange(labels.shape[0])[:, None] % 2 == 0)] = 0  # every other row void
    Image.fromarray(labels).save(labels_path)
    Image.fromarray(ids).save(ids_path)


@pytest.fixture(scope="module")
def tree(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("cityscapes")
    script = _toy_as_cityscapes()
    for split, count in (("train", 2), ("val", 3)):
        scenes = StreetScenes(split, count, (64, 128))
        for i in range(count):
            script.write_item(scenes, root, i)
    _edit(root / "gtFine" / "val" / "toy")
    return root


def _run(ckpt: Path, root: Path, out: Path, *extra: str) -> dict:
    evaluate_main(
        ["--ckpt_path", str(ckpt), "--data_root", str(root), "--cost", *RULES,
         "--classes", *CLASSES, "--output_dir", str(out), "--no-progress", *extra]
    )  # fmt: skip
    return json.loads((out / "results.json").read_text())


@pytest.mark.figures
def test_instance_rows_equal_the_brute_force_loop(tiny_run, tree, tmp_path) -> None:
    ckpt = find_checkpoint(None, runs_dir=tiny_run[2])
    results = _run(ckpt, tree, tmp_path / "eval", "--save-predictions")
    # the tree's own priors, counted from its train labels (not the toy checkpoint's)
    train = CityscapesSegmentation(tree, "train")
    priors = pixel_priors(train.read_label(i) for i in range(len(train)))
    _, roi = PriorMaps(priors).at((64, 128))
    classes = tuple(class_indices(["person", "car"]))
    gt, missed = {}, {}
    for path in sorted((tree / "gtFine" / "val" / "toy").glob(f"*{LABEL_SUFFIX}")):
        stem = path.name.removesuffix(LABEL_SUFFIX)
        target = LABEL_ID_TO_TRAIN_ID[np.array(Image.open(path))].astype(np.int64)
        ids = np.array(Image.open(path.with_name(stem + INSTANCE_SUFFIX))).astype(np.int64)
        saved = [tmp_path / "eval" / "predictions" / r / f"{stem}.png" for r in RULES]
        preds = np.stack([LABEL_ID_TO_TRAIN_ID[np.array(Image.open(p))] for p in saved])
        preds = preds.astype(np.int64)
        g, m, _ = reference_instances(preds, target, ids, roi.numpy(), classes)
        for key, v in g.items():
            gt[key] = gt.get(key, 0) + v
        for key, v in m.items():
            missed[key] = missed.get(key, 0) + v
    names = dict(zip(("person", "car"), classes, strict=True))
    rows = [r for r in results["rows"] if r["class"] in names]
    assert rows and all("gt_instances" in r for r in rows)
    assert not any("gt_instances" in r for r in results["rows"] if r["class"] == "building")
    for r in rows:
        k, cls, roi_id = RULES.index(r["matrix"]), names[r["class"]], r["roi"]
        want_gt = sum(gt.get((cls, s, roi_id), 0) for s in SIZES)
        by_size = [missed.get((k, cls, s, roi_id), 0) for s in SIZES]
        assert r["gt_instances"] == want_gt
        assert [r[f"missed_{s}"] for s in SIZES] == by_size
        assert r["missed_instances"] == sum(by_size)
    assert sum(gt.get((classes[0], s, 0), 0) for s in SIZES) > 0
    assert "instance metrics for person, car" in results["instances"]
    assert "missed_instances" in (tmp_path / "eval" / "table.md").read_text()
    assert (tmp_path / "eval" / "figures" / "missed_instances.png").is_file()


def test_mc_dropout_is_stated_and_reproducible(tiny_run, tree, tmp_path) -> None:
    ckpt = find_checkpoint(None, runs_dir=tiny_run[2])
    runs = [
        _run(ckpt, tree, tmp_path / f"mc{i}", "--mc_dropout", "3", "--seed", "5") for i in (0, 1)
    ]
    assert runs[0]["rows"] == runs[1]["rows"]
    for results in runs:
        assert (
            "Monte-Carlo dropout" in results["probabilities"]
            and "seed 5" in results["probabilities"]
        )
        assert results["source"]["mc_dropout"] == {"passes": 3, "seed": 5}
        assert results["options"]["mc_dropout"] == 3
    assert "Monte-Carlo dropout" in (tmp_path / "mc0" / "table.md").read_text()


def test_missing_instance_files_leave_the_metrics_out(tiny_run, tree, tmp_path) -> None:
    for path in (tree / "gtFine" / "val" / "toy").glob(f"*{INSTANCE_SUFFIX}"):
        path.rename(path.with_suffix(".bak"))
    try:
        ckpt = find_checkpoint(None, runs_dir=tiny_run[2])
        results = _run(ckpt, tree, tmp_path / "none")
    finally:
        for path in (tree / "gtFine" / "val" / "toy").glob("*.bak"):
            path.rename(path.with_suffix(".png"))
    assert "instance metrics absent: 3 of 3 images" in results["instances"]
    assert not any("gt_instances" in r for r in results["rows"])


def test_an_instance_target_without_its_class_is_refused(tiny_run, tree, tmp_path, capsys) -> None:
    ckpt = find_checkpoint(None, runs_dir=tiny_run[2])
    with pytest.raises(SystemExit) as exit_info:
        _run(ckpt, tree, tmp_path / "bad", "--sweep", "0.5", "--target",
             "rider:roi1:instance_recall>=0.9", "--maximize", "person:roi1:precision")  # fmt: skip
    assert exit_info.value.code == 2
    assert "'rider' in --classes" in capsys.readouterr().err


def test_mc_dropout_refusals_are_one_line(tmp_path, capsys) -> None:
    with pytest.raises(SystemExit) as exit_info:
        evaluate_main(["--probs", str(tmp_path), "--data_root", str(tmp_path), "--mc_dropout", "2"])
    assert exit_info.value.code == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "saved probabilities" in err


@pytest.mark.figures
def test_sweep_draws_and_targets_instance_recall(tiny_run, tree, tmp_path) -> None:
    ckpt = find_checkpoint(None, runs_dir=tiny_run[2])
    out = tmp_path / "sweep"
    _run(ckpt, tree, out, "--sweep", "0.5", "--target", "person:roi0:instance_recall>=0.0",
         "--maximize", "person:roi0:instance_recall")  # fmt: skip
    best = json.loads((out / "best.json").read_text())
    sweep = json.loads((out / "sweep.json").read_text())["rows"]
    recalls = [r["instance_recall"] for r in sweep if r["class"] == "person" and r["roi"] == 0]
    assert len(recalls) == 6 and best["found"] and best["value"] == max(recalls)
    assert (out / "figures" / "ternary_person_roi1_instance_recall.png").is_file()
