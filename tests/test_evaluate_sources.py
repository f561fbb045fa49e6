"""`evaluate.py` on another network's probabilities: VainF checkpoints, saved probability files,
and the official Cityscapes evaluator reading the saved predictions."""

import json
from pathlib import Path

import numpy as np
import pytest
from conftest import write_cityscapes_item

from costseg.classes import CLASS_NAMES
from costseg.cli import evaluate_main
from costseg.data.cityscapes import CityscapesSegmentation
from costseg.networks.probs_files import load_probs

ARGS = ["--no-progress", "--num_examples", "1", "--cost", "robotistic", "egoistic", "ml"]


@pytest.fixture(scope="module")
def vainf_file(vainf) -> Path:
    return vainf[1]


def _json(folder: Path, name: str) -> dict:
    return json.loads((folder / name).read_text())


def test_saved_probabilities_reproduce_the_direct_evaluation(vainf_file, cityscapes_root, tmp_path):
    data = ["--data_root", str(cityscapes_root)]
    direct, again = tmp_path / "direct", tmp_path / "again"
    evaluate_main([*ARGS, *data, "--network", f"vainf:{vainf_file}", "--save-probs",
                   "--sweep", "0.5", "--output_dir", str(direct)])  # fmt: skip
    assert len(list((direct / "probs").glob("*.npz"))) == 3
    evaluate_main([*ARGS, *data, "--probs", str(direct / "probs"), "--sweep", "0.5",
                   "--output_dir", str(again)])  # fmt: skip
    first, second = _json(direct, "results.json"), _json(again, "results.json")
    for key in ("rows", "confusion_matrix", "miou", "iou", "nll", "brier", "ece_per_class"):
        assert first[key] == second[key], key
    assert _json(direct, "sweep.json")["rows"] == _json(again, "sweep.json")["rows"]
    # NLL and Brier score (docs/definitions.md §13): a loop over the saved files' pixels.
    nll, brier, dataset = [], [], CityscapesSegmentation(cityscapes_root, "val")
    for name, (_, label) in zip(dataset.names, dataset, strict=True):
        probs = load_probs(direct / "probs" / f"{name}.npz").double().numpy()
        for (y, x), t in np.ndenumerate(label.numpy()):
            if t != 255:
                nll.append(-np.log(max(probs[t, y, x], 1e-12)))
                brier.append(((probs[:, y, x] - np.eye(19)[t]) ** 2).sum())
    assert first["nll"]["raw"] == pytest.approx(np.mean(nll), rel=1e-6)
    assert first["brier"]["raw"] == pytest.approx(np.mean(brier), rel=1e-6)


def test_probs_folder_missing_an_image_names_it(vainf_file, cityscapes_root, tmp_path, capsys):
    data = ["--data_root", str(cityscapes_root)]
    out = tmp_path / "direct"
    evaluate_main([*ARGS, *data, "--network", f"vainf:{vainf_file}", "--save-probs",
                   "--output_dir", str(out)])  # fmt: skip
    (out / "probs" / "lindau_000000_000019.npz").unlink()
    with pytest.raises(SystemExit) as exit_info:
        evaluate_main([*ARGS, *data, "--probs", str(out / "probs"), "--output_dir",
                       str(tmp_path / "again")])  # fmt: skip
    assert exit_info.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "lindau_000000_000019" in err[0], err


def test_official_cityscapes_evaluator_agrees(vainf_file, tmp_path):
    """cityscapesscripts reads the label-id PNGs of --save-predictions: same mIoU and IoUs."""
    ev = pytest.importorskip(
        "cityscapesscripts.evaluation.evalPixelLevelSemanticLabeling",
        reason="cityscapesscripts (a dev dependency) is not installed",
    )
    root = tmp_path / "cityscapes"
    names = ["aachen_000000_000019", "bochum_000000_000313", "zurich_000000_000001"]
    for split in ("train", "val"):
        for item, name in enumerate(names):
            write_cityscapes_item(root, split, name, item, valid_only=True)
    out = tmp_path / "out"
    evaluate_main([*ARGS, "--network", f"vainf:{vainf_file}", "--data_root", str(root),
                   "--save-predictions", "--output_dir", str(out)])  # fmt: skip
    args = ev.args
    args.evalInstLevelScore = args.evalPixelAccuracy = args.JSONOutput = False
    args.quiet, args.colorized, args.bold, args.nocol = True, False, "", ""
    gt = sorted(str(p) for p in (root / "gtFine" / "val").rglob("*_gtFine_labelIds.png"))
    pred = [str(out / "predictions" / "egoistic" / f"{Path(p).name[:-20]}.png") for p in gt]
    official = ev.evaluateImgLists(pred, gt, args)
    ours = _json(out, "results.json")
    assert abs(official["averageScoreClasses"] - ours["miou"]["egoistic"]) < 1e-9
    for name in CLASS_NAMES:
        theirs, mine = official["classScores"][name], ours["iou"]["egoistic"][name]
        assert (np.isnan(theirs) and mine is None) or abs(theirs - mine) < 1e-9, name
