"""`evaluate.py --defer` end to end on the tiny checkpoint: the columns of deferral in
results.json against a brute-force count over the saved predictions, nothing changed by a defer
cost too high to pay, the refusals, and a defer row in training's validation."""

from __future__ import annotations

import csv
import json
import math

import numpy as np
import pytest
import torch
from PIL import Image
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator
from test_cli_errors import _one_line

from costseg.checkpoints import find_checkpoint
from costseg.classes import CLASS_NAMES, LABEL_ID_TO_TRAIN_ID, ROI_NAMES
from costseg.cli import evaluate_main
from costseg.costs import save_cost, symmetric_cost, with_defer
from costseg.decision.label_maps import DEFERRED
from costseg.rules import parse_rules, rules_group

DEFER = "0.8"  # the 2-step network is unsure: at 0.8 robotistic and ml defer some pixels
RULES = ["robotistic", "altruistic", "ml"]  # altruistic's costs dwarf 0.8: it defers every pixel


def _evaluate(ckpt: str, out, *extra: str, rules=RULES):
    args = ["--ckpt_path", ckpt, "--cost", *rules, "--output_dir", str(out), "--no-progress"]
    return evaluate_main([*args, *extra])


@pytest.fixture(scope="module")
def ckpt(tiny_run) -> str:
    return str(find_checkpoint(None, runs_dir=tiny_run[2]))


@pytest.fixture(scope="module")
def deferred(ckpt, tmp_path_factory):
    out = tmp_path_factory.mktemp("deferred")
    extra = ["--defer", DEFER, "--save-predictions", "--num_examples", "3", "--temperature_sweep"]
    return _evaluate(ckpt, out, *extra), out


def _ratio(a: int, b: int) -> float | None:
    return a / b if b else None  # JSON writes NaN as null


def test_defer_columns_equal_a_count_over_the_saved_predictions(deferred) -> None:
    results, out = deferred
    record = json.loads((out / "results.json").read_text())
    assert record["defer"] == {r: float(DEFER) for r in RULES}
    roi = results.roi.numpy()
    labels = {ex.name: ex.label.numpy() for ex in results.examples}
    assert len(labels) == results.num_images == 3
    rows = {(r["matrix"], r["class"], r["roi"]): r for r in record["rows"]}
    shares = []
    for rule in RULES:
        folder = out / "predictions" / rule
        preds = {s: LABEL_ID_TO_TRAIN_ID[np.array(Image.open(folder / f"{s}.png"))] for s in labels}
        gt = np.concatenate([labels[s].ravel() for s in labels])
        pred = np.concatenate([preds[s].ravel() for s in labels])
        where = np.concatenate([roi.ravel()] * len(labels))
        valid, deferred_px = gt != 255, pred == DEFERRED
        shares.append((deferred_px & valid).sum() / valid.sum())
        for name in ("person", "building"):
            c = CLASS_NAMES.index(name)
            for r in range(len(ROI_NAMES)):
                inside = valid & ((where == r) if r else True)
                count = lambda m, inside=inside: int((inside & m).sum())  # noqa: E731
                is_c = gt == c
                g, d, tp = count(is_c), count(is_c & deferred_px), count(is_c & (pred == c))
                row = rows[rule, name, r]
                assert row["defer"] == float(DEFER)
                assert row["recall"] == _ratio(tp, g)
                assert row["precision"] == _ratio(tp, count(pred == c))
                assert row["coverage"] == _ratio(g - d, g)
                assert row["selective_recall"] == _ratio(tp, g - d)
                assert row["handled_recall"] == _ratio(tp + d, g)
                assert row["deferred_rate"] == _ratio(count(deferred_px), count(valid))
        for c, name in enumerate(CLASS_NAMES):  # IoU: a deferred pixel is a false negative
            tp, g, p = (
                int((valid & m).sum()) for m in ((gt == c) & (pred == c), gt == c, pred == c)
            )
            assert record["iou"][rule][name] == _ratio(tp, g + p - tp), (rule, name)
    assert 0 < shares[0] < 1 and shares[1] == 1 and 0 < shares[2] < 1


def test_the_outputs_state_deferral(deferred) -> None:
    _, out = deferred
    table = (out / "table.md").read_text()
    assert "| defer |" in table and "handled_recall" in table and "deferred (whole image)" in table
    with (out / "temperature_sweep.csv").open() as f:
        sweep = list(csv.DictReader(f))
    assert {"defer", "coverage", "deferred_rate"} <= set(sweep[0]) and sweep[0]["defer"] == DEFER
    for name in ("masks_0", "cost_robotistic", "cost_ml"):
        with Image.open(out / "figures" / f"{name}.png") as png:
            assert png.width > 100
    events = EventAccumulator(str(out), size_guidance={"scalars": 0})
    events.Reload()
    assert "temperature_sweep/robotistic@T=0.50/deferred_rate" in events.Tags()["scalars"]


def test_a_defer_cost_too_high_to_pay_changes_nothing(ckpt, tmp_path) -> None:
    few = ["--num_examples", "0", "--classes", "person"]  # fewer figures to draw
    _evaluate(ckpt, tmp_path / "plain", *few, rules=RULES[::2])
    never = _evaluate(ckpt, tmp_path / "never", *few, "--defer", "1e9", rules=RULES[::2])
    assert int(never.named.pixels["deferred"].sum()) == 0
    a, b = (json.loads((tmp_path / d / "results.json").read_text()) for d in ("plain", "never"))
    assert "defer" not in a and "coverage" not in a["rows"][0]  # no rule defers: no columns
    for key in ("miou", "iou", "confusion_matrix"):
        assert a[key] | {"layout": ""} == b[key] | {"layout": ""}, key
    for row, same in zip(a["rows"], b["rows"], strict=True):
        assert {k: same[k] for k in row} == row
        assert same["deferred_rate"] == 0 and same["coverage"] in (1, None)


def test_bad_defer_options_give_one_line(ckpt, tmp_path, capsys) -> None:
    run = ["--ckpt_path", ckpt, "--no-progress", "--output_dir", str(tmp_path / "out")]
    for value in ("-1", "abc", "inf"):
        _one_line(evaluate_main, [*run, "--defer", value], capsys, "--defer", repr(value))
    chow = tmp_path / "chow.yaml"
    save_cost(chow, with_defer(symmetric_cost(19), 0.5), "chow")
    _one_line(evaluate_main, [*run, "--cost", str(chow), "--defer", "0.3"], capsys, "leave it out")
    alpha = ["--alpha_sweep", "0.5", "--alpha_cost", str(chow)]
    _one_line(evaluate_main, [*run, *alpha], capsys, "--alpha_cost", "defer row")
    vertices = ["--sweep", "0.5", "--vertices", "robotistic", "altruistic", str(chow)]
    _one_line(evaluate_main, [*run, *vertices], capsys, "vertex", "defer row")
    assert not (tmp_path / "out").exists()  # refused before any output


def test_a_cost_file_with_per_class_defer_costs(tmp_path) -> None:
    row = torch.full((19,), 0.5)
    row[11] = 0.05
    path = tmp_path / "careful.yaml"
    save_cost(path, with_defer(symmetric_cost(19), row), "careful")
    group = rules_group(parse_rules([str(path), "robotistic"]))
    assert group.defers and group.columns[1] == {"matrix": "robotistic", "defer": None}
    assert group.columns[0]["defer"] == row.tolist()


def test_validation_takes_a_rule_that_defers(tmp_path) -> None:
    from costseg.models.deeplabv3plus import DeepLabV3Plus
    from costseg.training.module import SegmentationModule

    chow = tmp_path / "chow.yaml"
    save_cost(chow, with_defer(symmetric_cost(19), 0.1), "chow")  # defers where max p < 0.9
    torch.manual_seed(0)
    rules = ("robotistic", str(chow))
    net = DeepLabV3Plus(19, "resnet18", decoder_channels=16)
    module = SegmentationModule(net, val_costs=rules, channels_last=False)
    logged = {}
    module.log = lambda name, value, **_: logged.__setitem__(name, float(value))
    images = torch.randint(0, 256, (2, 3, 32, 64), dtype=torch.uint8)
    labels = torch.randint(0, 19, (2, 32, 64))
    with torch.no_grad():
        preds = module.eval().validation_step((images, labels), 0)["preds"]
    module.on_validation_epoch_end()
    share = (preds[:, 1] == DEFERRED).double().mean().item()
    assert share > 0 and math.isclose(logged["val/deferred_rate/chow"], share, rel_tol=1e-6)
    assert "val/deferred_rate/robotistic" not in logged and (preds[:, 0] != DEFERRED).all()
