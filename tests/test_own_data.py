"""A researcher's own data: images of another size than their labels, no train split (priors from a
file, or the geometric RoI map), a checkpoint's priors kept to the data they were counted on, and
saved probabilities of the procedural scenes evaluated again without ``--data_root``."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import CITYSCAPES_FILES, write_cityscapes_item
from PIL import Image
from torch.nn import functional as F

from costseg.checkpoints import find_checkpoint
from costseg.classes import CLASS_NAMES
from costseg.cli import evaluate_main
from costseg.data.cityscapes import CityscapesSegmentation
from costseg.data.priors import geometric_roi_map, read_priors_file
from costseg.networks import load_network

LABEL_SIZE = (32, 64)
ROOT = Path(__file__).resolve().parents[1]
ARGS = ["--no-progress", "--num_examples", "1", "--cost", "robotistic", "--classes", "road"]


def _tree(root: Path, image_size: tuple[int, int], train: bool = True) -> Path:
    """A Cityscapes-layout tree with labels of ``LABEL_SIZE`` and images of ``image_size``."""
    for split, names in CITYSCAPES_FILES.items():
        if split == "train" and not train:
            continue
        for item, name in enumerate(names):
            image, _ = write_cityscapes_item(root, split, name, item, LABEL_SIZE)
            with Image.open(image) as full:
                full.resize(image_size[::-1], Image.Resampling.BILINEAR).save(image)
    return root


@pytest.fixture(scope="module")
def network(tiny_run) -> str:
    return f"costseg:{find_checkpoint(None, runs_dir=tiny_run[2])}"


@pytest.fixture(scope="module")
def counted(tmp_path_factory) -> tuple[Path, Path]:
    """A tree with train and val labels of ``LABEL_SIZE`` and the priors scripts/count_priors.py
    counts on its train labels, once for the module."""
    root = _tree(tmp_path_factory.mktemp("own") / "cs", LABEL_SIZE)
    priors, labels = root.parent / "p.pt", root / "gtFine" / "train"
    script = ROOT / "scripts" / "count_priors.py"
    subprocess.run([sys.executable, script, str(labels), "--output", str(priors)], check=True)
    return root, priors


def _results(out: Path) -> dict:
    return json.loads((out / "results.json").read_text())


def _fails(args: list[str], capsys) -> str:
    with pytest.raises(SystemExit) as exit_info:
        evaluate_main(args)
    assert exit_info.value.code == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1
    return lines[0]


def test_half_size_images_are_scored_at_label_size(network, tmp_path, capsys):
    """Logits of 16 x 32 images, resized bilinearly to the 32 x 64 labels, then argmax: the
    confusion matrix of a per-pixel loop, and the resizing said once on the terminal and in
    results.json."""
    root, out = _tree(tmp_path / "cs", (16, 32)), tmp_path / "out"
    evaluate_main([*ARGS, "--network", network, "--data_root", str(root), "--output_dir", str(out)])
    said = [line for line in capsys.readouterr().out.splitlines() if "differ in size" in line]
    assert said == ["images and labels differ in size: logits resized bilinearly 16x32 -> 32x64"]
    results = _results(out)
    assert results["source"]["resized_to_labels"] == ["16x32 -> 32x64"]
    net, expected = load_network(network), np.zeros((19, 19), dtype=np.int64)
    for image, label in CityscapesSegmentation(root, "val"):
        assert image.shape[-2:] == (16, 32) and label.shape == LABEL_SIZE
        with torch.no_grad():
            logits = F.interpolate(net(image[None]), size=LABEL_SIZE, mode="bilinear")
        for p, y in zip(
            logits[0].argmax(0).flatten().tolist(), label.flatten().tolist(), strict=True
        ):
            if y != 255:
                expected[y, p] += 1
    assert np.array_equal(np.array(results["confusion_matrix"]["robotistic"]), expected)
    saved, again = tmp_path / "saved", tmp_path / "again"  # saved at the labels' size, read
    evaluate_main([*ARGS, "--network", network, "--data_root", str(root), "--save-probs",
                   "--output_dir", str(saved)])  # fmt: skip
    evaluate_main([*ARGS, "--probs", str(saved / "probs"), "--output_dir", str(again)])
    assert _results(again)["confusion_matrix"] == _results(saved)["confusion_matrix"]


def test_no_train_split_is_refused_in_one_line_naming_the_options(network, tmp_path, capsys):
    root = _tree(tmp_path / "cs", LABEL_SIZE, train=False)
    line = _fails([*ARGS, "--network", network, "--data_root", str(root)], capsys)
    assert line.startswith("error: no pixel-wise priors for")
    assert "--priors FILE" in line and "--roi geometric" in line
    line = _fails([*ARGS, "--network", network, "--data_root", str(root), "--roi", "geometric",
                   "--cost", "ml"], capsys)  # fmt: skip
    assert "--priors FILE" in line and "--roi geometric" not in line
    line = _fails([*ARGS, "--network", network, "--priors", str(tmp_path / "none.pt")], capsys)
    assert line == f"error: --priors file not found: {tmp_path / 'none.pt'}"


def test_geometric_roi_map_without_training_labels(network, tmp_path):
    """The street RoI's road recall equals a loop over the pixels of the geometric map."""
    root, out = _tree(tmp_path / "cs", LABEL_SIZE, train=False), tmp_path / "out"
    evaluate_main([*ARGS, "--network", network, "--data_root", str(root), "--roi", "geometric",
                   "--output_dir", str(out)])  # fmt: skip
    results = _results(out)
    assert results["source"]["priors"] == "none: no training labels"
    row = next(r for r in results["rows"] if r["roi"] == 1)
    net, roi = load_network(network), geometric_roi_map(LABEL_SIZE)
    tp = fn = 0
    for image, label in CityscapesSegmentation(root, "val"):
        with torch.no_grad():
            pred = net(image[None])[0].argmax(0)
        inside = (roi == 1) & (label == 0)
        tp += int((inside & (pred == 0)).sum())
        fn += int((inside & (pred != 0)).sum())
    assert row["recall"] == (pytest.approx(tp / (tp + fn)) if tp + fn else None)


def test_priors_from_a_file_equal_the_counted_ones_and_a_toy_checkpoint_lends_none(
    network, counted, tmp_path, capsys
):
    """scripts/count_priors.py on the train labels writes the priors the evaluation counts
    itself; the toy checkpoint's own priors are not used for Cityscapes data; ml decides the
    same with either."""
    (root, priors), own, from_file = counted, tmp_path / "counted", tmp_path / "file"
    common = [*ARGS, "--network", network, "--data_root", str(root), "--cost", "ml"]
    evaluate_main([*common, "--output_dir", str(own)])
    assert "counted on other data: not used" in capsys.readouterr().out
    cached = next((tmp_path / "priors").glob("train_*.pt"))
    torch.testing.assert_close(_priors(priors), _priors(cached), rtol=0, atol=0)
    evaluate_main([*common, "--priors", str(priors), "--output_dir", str(from_file)])
    first, second = _results(own), _results(from_file)
    assert first["source"]["priors"]["data"]["init_args"]["root"] == str(root.resolve())
    assert second["source"]["priors"]["file"] == str(priors.resolve())
    assert first["confusion_matrix"] == second["confusion_matrix"]
    assert first["rows"] == second["rows"]


def _priors(path: Path) -> torch.Tensor:
    return read_priors_file(path, CLASS_NAMES)["priors"]


def test_saved_probabilities_of_the_procedural_scenes_need_no_data_root(network, tmp_path):
    direct, again = tmp_path / "direct", tmp_path / "again"
    common = ["--no-progress", "--num_examples", "1", "--cost", "robotistic", "ml", "--limit", "2"]
    evaluate_main([*common, "--network", network, "--save-probs", "--output_dir", str(direct)])
    evaluate_main([*common, "--probs", str(direct / "probs"), "--output_dir", str(again)])
    first, second = _results(direct), _results(again)
    for key in ("rows", "confusion_matrix", "miou", "nll"):
        assert first[key] == second[key], key


def test_python_api_equals_the_command_line(network, counted, tmp_path):
    """costseg.evaluate(module, dataset) gives the rows of evaluate.py on the same network,
    data and priors."""
    import costseg

    (root, priors), cli, api = counted, tmp_path / "cli", tmp_path / "api"
    rules = ["robotistic", "ml"]
    evaluate_main([*ARGS, "--cost", *rules, "--network", network, "--data_root", str(root),
                   "--priors", str(priors), "--output_dir", str(cli)])  # fmt: skip
    results = costseg.evaluate(
        load_network(network), CityscapesSegmentation(root, "val"), rules, priors=priors,
        classes=["road"], num_examples=1, progress=False, output_dir=str(api),
    )  # fmt: skip
    assert results.output_dir == api
    assert _results(api)["rows"] == _results(cli)["rows"]
    with pytest.raises(ValueError, match="unknown option 'no_such'"):
        costseg.evaluate(load_network(network), CityscapesSegmentation(root, "val"), no_such=1)
    with pytest.raises(ValueError, match=r"\(3, H, W\) uint8 RGB image"):
        costseg.evaluate(load_network(network), [(torch.zeros(3, 4, 4), torch.zeros(4, 4))])


def test_the_python_example_of_usage_md_runs(tmp_path):
    text = (ROOT / "docs" / "usage.md").read_text()
    section = text[text.index("### Your own network and dataset, from Python") :]
    code = section.split("```python\n", 1)[1].split("```", 1)[0]
    (tmp_path / "example.py").write_text(code)
    run = subprocess.run([sys.executable, "example.py"], cwd=tmp_path, capture_output=True,
                         text=True, timeout=300)  # fmt: skip
    assert run.returncode == 0, run.stderr
    assert (tmp_path / "eval" / "my_network" / "results.json").is_file()
    assert not (tmp_path / "eval" / "my_network" / "INCOMPLETE").exists()


def test_python_predict_equals_predict_py_with_the_same_priors(network, counted, tmp_path):
    """costseg.predict(module, inputs, priors=tensor) writes the label maps of predict.py with
    --priors FILE."""
    import costseg
    from costseg.cli import predict_main

    root, priors_file = counted
    images = root / "leftImg8bit" / "val"
    cli, api = tmp_path / "cli", tmp_path / "api"
    rules = ["robotistic", "ml"]
    predict_main(["--input", str(images), "--network", network, "--cost", *rules, "--priors",
                  str(priors_file), "--output_dir", str(cli), "--no-progress"])  # fmt: skip
    out = costseg.predict(load_network(network), [images], rules, priors=_priors(priors_file),
                          output_dir=str(api), progress=False)  # fmt: skip
    assert out == api
    written = sorted(p.relative_to(cli) for p in (cli / "labels").rglob("*.png"))
    assert len(written) == 2 * len(CITYSCAPES_FILES["val"])
    for path in written:
        assert np.array_equal(
            np.asarray(Image.open(cli / path)), np.asarray(Image.open(api / path))
        )
