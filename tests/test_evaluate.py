"""`python evaluate.py` end to end on a tiny checkpoint: files, TensorBoard, PNGs, sweeps."""

import json

import numpy as np
import pytest
import torch
import yaml
from PIL import Image
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

from costseg.checkpoints import find_checkpoint
from costseg.classes import CLASS_NAMES, LABEL_ID_TO_TRAIN_ID
from costseg.cli import evaluate_main
from costseg.costs import load_cost, mix_costs, save_cost
from costseg.data.toy import StreetScenes
from costseg.eval_job import EvalOptions, run
from costseg.rules import apply_rules, parse_rules


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
    scalars = events.Tags()["scalars"]
    for tag in ("evaluation/miou/egoistic", "evaluation/person/roi0/fn_segments/ml"):
        assert tag in scalars
    images = events.Tags()["images"]
    assert "evaluation/masks/0" in images and "evaluation/fp_segments" in images
    assert any("evaluation/table" in t for t in events.Tags()["tensors"])


def test_prediction_pngs_decode_to_the_same_labels(evaluated):
    ckpt, out = evaluated
    from costseg.module import SegmentationModule

    module = SegmentationModule.load_from_checkpoint(ckpt, map_location="cpu").eval()
    image, label = StreetScenes("val", 3, (64, 128))[1]
    rules = parse_rules(["altruistic", "ml"])
    with torch.no_grad():
        probs = module(image[None]).softmax(1)
    priors, _ = module.priors_at(label.shape)
    expected = apply_rules(probs, rules, priors)[0]
    for k, name in enumerate(("altruistic", "ml")):
        label_ids = np.array(Image.open(out / "predictions" / name / "val_000001.png"))
        assert torch.equal(torch.from_numpy(LABEL_ID_TO_TRAIN_ID[label_ids]).long(), expected[k])


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
        ckpt_path=str(find_checkpoint(None, runs_dir=runs)),
        output_dir=str(tmp_path / "out"),
        sweep=0.25,
        num_examples=0,
        progress=False,
    )
    result = run(opts)
    weights = result["info"]["weights"].tolist()
    single, sweep = result["results"]
    for k, w in enumerate([[1, 0, 0], [0, 1, 0], [0, 0, 1], *interior.tolist()]):
        j = weights.index(w)
        assert torch.equal(single["pixels"]["confmat"][k], sweep["pixels"]["confmat"][j])
        for key in ("fp", "fn", "n_pred", "n_gt"):
            assert torch.equal(single["segments"][key][k], sweep["segments"][key][j])
    rows = json.loads((tmp_path / "out" / "sweep.json").read_text())["rows"]
    assert len(rows) == 15 * 2 * 3
    with Image.open(tmp_path / "out" / "figures" / "ternary_person_roi1_recall.png") as png:
        assert png.format == "PNG" and png.width >= 300


def _fails(args, capsys, *needles):
    with pytest.raises(SystemExit) as exit_info:
        evaluate_main([*args, "--no-progress"])
    assert exit_info.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert any(all(n in line for n in needles) for line in err), err
    return err


def test_bad_inputs_end_with_one_line_and_status_2(tiny_run, tmp_path, capsys, monkeypatch):
    ckpt = ["--ckpt_path", str(find_checkpoint(None, runs_dir=tiny_run[2]))]
    _fails([*ckpt, "--cost", "selfish"], capsys, "unknown cost 'selfish'", "robotistic", "ml")
    bad = tmp_path / "bad.yaml"
    matrix = (1 - torch.eye(19)).tolist()
    matrix[11][2] = -5
    bad.write_text(yaml.safe_dump({"classes": list(CLASS_NAMES), "matrix": matrix}))
    _fails([*ckpt, "--cost", str(bad)], capsys, "entry [11, 2]", "person", "building")
    small = tmp_path / "small.yaml"
    small.write_text(yaml.safe_dump({"classes": ["road", "car"], "matrix": [[0, 1], [1, 0]]}))
    _fails([*ckpt, "--cost", str(small)], capsys, "19 classes")
    _fails([*ckpt, "--classes", "person", "unicorn"], capsys, "unknown class 'unicorn'")
    _fails(
        [
            *ckpt,
            "--sweep",
            "0.5",
            "--target",
            "person:roi9:recall>=1",
            "--maximize",
            "person:roi1:precision",
        ],
        capsys,
        "unknown RoI 'roi9'",
    )
    _fails(
        [
            *ckpt,
            "--sweep",
            "0.5",
            "--target",
            "person:roi1:recall about 1",
            "--maximize",
            "person:roi1:precision",
        ],
        capsys,
        "cannot parse",
    )
    _fails(
        [
            *ckpt,
            "--sweep",
            "0.5",
            "--target",
            "person:roi1:sharpness>=1",
            "--maximize",
            "person:roi1:precision",
        ],
        capsys,
        "unknown metric 'sharpness'",
    )
    monkeypatch.chdir(tmp_path)
    _fails([], capsys, "no last.ckpt found", "python train.py")
