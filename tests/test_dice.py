"""Dice (F1) per class and RoI: torchmetrics' F1 score, and in every output of an evaluation."""

from __future__ import annotations

import json

import torch
from torchmetrics.functional.classification import multiclass_f1_score

from costseg.checkpoints import find_checkpoint
from costseg.cli import evaluate_main
from costseg.metrics import RoIPrecisionRecall


def test_dice_is_torchmetrics_f1_score_per_class_and_roi():
    g = torch.Generator().manual_seed(0)
    preds = torch.randint(0, 5, (3, 16, 16), generator=g)
    target = torch.randint(0, 5, (3, 16, 16), generator=g)
    target[:, :2] = 255  # ignored
    roi = torch.randint(0, 3, (16, 16), generator=g)
    metric = RoIPrecisionRecall(num_classes=5, num_rois=2)
    metric.update(preds[:, None], target, roi)
    dice = metric.compute()["dice"][0]  # (R+1, N)
    for r in range(3):
        inside = torch.ones_like(roi, dtype=torch.bool) if r == 0 else roi == r
        t = torch.where(inside, target, 255)
        f1 = multiclass_f1_score(preds, t, 5, average="none", ignore_index=255, zero_division=0)
        present = (t == torch.arange(5)[:, None, None, None]).any((1, 2, 3)) | (
            (preds[:, None] == torch.arange(5)[None, :, None, None]) & (t != 255)[:, None]
        ).any((0, 2, 3))
        torch.testing.assert_close(dice[r][present], f1[present].double())
        assert dice[r][~present].isnan().all()  # 0/0 is NaN (definitions §4), not 0


def test_an_evaluation_reports_dice_in_its_files_and_tensorboard(tiny_run, tmp_path):
    out = tmp_path / "out"
    ckpt = str(find_checkpoint(None, runs_dir=tiny_run[2]))
    args = ["--ckpt_path", ckpt, "--cost", "robotistic", "egoistic", "--sweep", "0.5"]
    evaluate_main([*args, "--limit", "1", "--no-progress", "--output_dir", str(out)])
    rows = json.loads((out / "results.json").read_text())["rows"]
    defined = [r for r in rows if r["precision"] and r["recall"]]
    assert defined
    for row in defined:  # the harmonic mean of precision and recall
        p, r = row["precision"], row["recall"]
        assert abs(row["dice"] - 2 * p * r / (p + r)) < 1e-9
    header = (out / "table.md").read_text().split("| class | RoI | matrix |")[1].splitlines()[0]
    assert "| dice |" in header
    assert "dice" in (out / "results.csv").read_text().splitlines()[0].split(",")
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    tags = set()
    for folder in {p.parent for p in out.rglob("events.out.tfevents.*")}:
        tags |= set(EventAccumulator(str(folder)).Reload().Tags()["scalars"])
    assert any(tag.endswith("/dice_roi1") for tag in tags), sorted(tags)[:20]
    trained = tiny_run[1].callback_metrics
    assert "val/dice_street/robotistic/person" in trained, sorted(trained)[:20]
