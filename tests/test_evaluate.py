"""`python evaluate.py` end to end on a tiny checkpoint: files, TensorBoard, PNGs, sweeps."""

import json

import numpy as np
import pytest
import torch
from PIL import Image
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

from costseg.checkpoints import find_checkpoint
from costseg.classes import LABEL_ID_TO_TRAIN_ID
from costseg.cli import evaluate_main
from costseg.costs import load_cost, mix_costs, save_cost
from costseg.data.priors import resize_priors
from costseg.data.toy import StreetScenes
from costseg.decision import decide_reference
from costseg.evaluation.run import evaluate
from costseg.options import EvalOptions


@pytest.fixture(scope="module")
def evaluated(tiny_run, tmp_path_factory):
    _, _, runs = tiny_run
    out = tmp_path_factory.mktemp("evaluation")
    ckpt = find_checkpoint(None, runs_dir=runs)
    evaluate_main(
        [
            "--ckpt_path",
            str(ckpt),
            "--cost",
            "robotistic",
            "altruistic",
            "egoistic",
            "ml",
            "--output_dir",
            str(out),
            "--save-predictions",
            "--no-progress",
            "--num_examples",
            "2",
        ]
    )
    return ckpt, out


def test_result_files(evaluated):
    _, out = evaluated
    results = json.loads((out / "results.json").read_text())
    rows = results["rows"]
    # 4 rules x 2 classes x 5 RoIs, the undefined ratios as null (never 0 or 1)
    assert len(rows) == 40
    assert {r["matrix"] for r in rows} == {"robotistic", "altruistic", "egoistic", "ml"}
    assert all(r["precision"] is None or 0 <= r["precision"] <= 1 for r in rows)
    table = (out / "table.md").read_text()
    assert "41.12" in table  # the paper's numbers stand next to ours
    assert (out / "results.csv").read_text().count("\n") == 41
    for name in ("fp_segments", "fn_segments", "masks_0", "masks_1", "cost_egoistic", "roi_map"):
        with Image.open(out / "figures" / f"{name}.png") as png:
            assert png.width > 100 and png.height > 100


def test_tensorboard_holds_scalars_images_and_table(evaluated):
    _, out = evaluated
    events = EventAccumulator(str(out), size_guidance={"images": 0, "scalars": 0, "tensors": 0})
    events.Reload()
    assert events.Tags()["scalars"] == []  # no sweep: every number is in the tables
    images = events.Tags()["images"]
    assert "evaluation/masks/0" in images and "evaluation/fp_segments" in images
    assert any("evaluation/table" in t for t in events.Tags()["tensors"])
    assert any("evaluation/results" in t for t in events.Tags()["tensors"])


def test_prediction_pngs_decode_to_the_same_labels(evaluated):
    """The label-id PNGs decode to the float64 reference rule on the network's probabilities."""
    ckpt, out = evaluated
    from costseg.training.module import SegmentationModule

    module = SegmentationModule.load_from_checkpoint(ckpt, map_location="cpu").eval()
    image, label = StreetScenes("val", 3, (64, 128))[1]
    with torch.no_grad():
        probs = module(image[None]).softmax(1)
    expected = {
        "altruistic": decide_reference(probs, load_cost("altruistic"))[0],
        "ml": decide_reference(probs, None, resize_priors(module.priors, tuple(label.shape)))[0],
    }
    for name, labels in expected.items():
        label_ids = np.array(Image.open(out / "predictions" / name / "val_000001.png"))
        assert torch.equal(torch.from_numpy(LABEL_ID_TO_TRAIN_ID[label_ids]).long(), labels)


@pytest.mark.figures
def test_sweep_points_equal_single_rule_evaluations(tiny_run, tmp_path):
    _, _, runs = tiny_run
    vertices = torch.stack([load_cost(n) for n in ("robotistic", "altruistic", "egoistic")])
    interior = torch.tensor([[0.5, 0.25, 0.25], [0.0, 0.5, 0.5]], dtype=torch.float64)
    files = []
    for i, matrix in enumerate(mix_costs(vertices, interior)):
        files.append(str(tmp_path / f"mix{i}.yaml"))
        save_cost(files[-1], matrix, f"mix{i}")
    opts = EvalOptions(
        cost=["robotistic", "altruistic", "egoistic", *files],
        ckpt_path=[str(find_checkpoint(None, runs_dir=runs))],
        output_dir=str(tmp_path / "out"),
        sweep=0.25,
        num_examples=0,
        progress=False,
    )
    single, sweep = evaluate(opts).groups
    weights = sweep.group.weights.tolist()
    for k, w in enumerate([[1, 0, 0], [0, 1, 0], [0, 0, 1], *interior.tolist()]):
        j = weights.index(w)
        assert torch.equal(single.pixels["confmat"][k], sweep.pixels["confmat"][j])
        for key in ("fp", "fn", "n_pred", "n_gt"):
            assert torch.equal(single.segments[key][k], sweep.segments[key][j])
    rows = json.loads((tmp_path / "out" / "sweep.json").read_text())["rows"]
    assert len(rows) == 15 * 2 * 3
    with Image.open(tmp_path / "out" / "figures" / "ternary_person_roi1_recall.png") as png:
        assert png.format == "PNG" and png.width >= 300


def _fails(args, capsys, *needles):
    with pytest.raises(SystemExit) as exit_info:
        evaluate_main([*args, "--no-progress"])
    assert exit_info.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and all(n in err[0] for n in needles), err


def test_each_evaluation_gets_a_new_folder(tiny_run, tmp_path, monkeypatch, capsys):
    """Without --output_dir nothing is overwritten: version_0, version_1, ... (path printed)."""
    ckpt = find_checkpoint(None, runs_dir=tiny_run[2])
    copy = tmp_path / "run" / "checkpoints" / "last.ckpt"
    copy.parent.mkdir(parents=True)
    copy.write_bytes(ckpt.read_bytes())
    args = ["--ckpt_path", str(copy), "--cost", "robotistic", "--limit", "1", "--no-progress"]
    first = evaluate_main([*args, "--num_examples", "0"]).output_dir
    second = evaluate_main([*args, "--num_examples", "0"]).output_dir
    assert (first.name, second.name) == ("version_0", "version_1")
    assert first.parent == second.parent == tmp_path / "run" / "evaluation"
    assert (first / "results.json").is_file() and (second / "results.json").is_file()
    assert f"results written to {second}" in capsys.readouterr().out


def test_output_dir_with_results_needs_overwrite(tiny_run, tmp_path, capsys):
    ckpt = str(find_checkpoint(None, runs_dir=tiny_run[2]))
    out = tmp_path / "out"
    args = ["--ckpt_path", ckpt, "--cost", "robotistic", "--limit", "1", "--output_dir", str(out)]
    evaluate_main([*args, "--no-progress", "--num_examples", "0"])
    before = (out / "results.json").read_text()
    _fails(args, capsys, "already holds results", "--overwrite")
    assert (out / "results.json").read_text() == before  # nothing lost
    evaluate_main([*args, "--no-progress", "--num_examples", "0", "--overwrite"])


def test_images_of_different_sizes_in_one_evaluation(tiny_run, cityscapes_root, tmp_path):
    """Priors and RoIs are resized per image, FP/FN maps share one canvas, masks per image."""
    from conftest import write_cityscapes_item

    write_cityscapes_item(cityscapes_root, "val", "zurich_000000_000001", 3, size=(48, 80))
    write_cityscapes_item(cityscapes_root, "val", "zurich_000000_000002", 4, size=(16, 32))
    ckpt = str(find_checkpoint(None, runs_dir=tiny_run[2]))
    args = ["--ckpt_path", ckpt, "--data_root", str(cityscapes_root), "--cost", "robotistic"]
    args += ["ml", "--output_dir", str(tmp_path / "out"), "--no-progress", "--num_examples", "5"]
    results = evaluate_main([*args, "--batch_size", "5", "--save-predictions"])
    assert results.num_images == 5
    sizes = {tuple(ex.label.shape) for ex in results.examples}
    assert sizes == {(32, 64), (48, 80), (16, 32)}
    named = results.groups[0]
    assert named.segments["fp_map"].shape[-2:] == (32, 64)  # the first image's size
    # Every labelled pixel of every image was counted once per rule.
    labelled = sum(int((ex.label != 255).sum()) for ex in results.examples)
    assert int(named.pixels["confmat"][0, 0].sum()) == labelled
    with Image.open(tmp_path / "out" / "predictions" / "ml" / "zurich_000000_000001.png") as png:
        assert png.size == (80, 48)
