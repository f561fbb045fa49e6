"""Unknown objects in the procedural scenes and the anomaly metrics (docs/definitions.md §17)."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from sklearn.metrics import average_precision_score, roc_auc_score, roc_curve
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

from costseg.checkpoints import find_checkpoint
from costseg.cli import evaluate_main
from costseg.data.from_config import data_settings
from costseg.data.toy import StreetScenes
from costseg.metrics.anomaly import AnomalyMetrics
from costseg.metrics.functional.anomaly import BINS, TAUS, component_counts, component_metrics
from costseg.networks import load_costseg_checkpoint
from costseg.networks.probs_files import find_probs_file, load_probs

SIZE = (64, 128)


def test_unknown_objects_leave_the_scene_around_them_unchanged():
    plain, unknown = StreetScenes("val", 6, SIZE), StreetScenes("val", 6, SIZE, anomalies=True)
    assert unknown.has_anomalies and not plain.has_anomalies
    for i in range(6):
        image, label, ids, mask = unknown.with_anomalies(i)
        clean_image, clean_label = plain[i]
        assert set(mask.unique().tolist()) <= {0, 1, 255} and (mask == 1).any()
        objects = mask == 1
        assert (label[objects] == 255).all()  # no Cityscapes class is right there
        assert torch.equal(label[~objects], clean_label[~objects])  # the same scene around them
        assert torch.equal(mask == 255, (label == 255) & ~objects)
        assert not torch.equal(image, clean_image)
        assert torch.equal(unknown[i][0], image) and torch.equal(unknown[i][1], label)
        assert torch.equal(ids, unknown.with_instances(i)[2])
        assert (ids[objects] == 0).all()  # unlabelled in Cityscapes' instance encoding


def test_scenes_without_unknown_objects_have_no_mask():
    with pytest.raises(ValueError, match="anomalies=True"):
        StreetScenes("val", 1, SIZE).with_anomalies(0)


def _on_bin_centres(values: np.ndarray) -> np.ndarray:
    """Scores in the middle of their bins: binning loses nothing, so sklearn sees the same."""
    return (np.floor(values * BINS).clip(max=BINS - 1) + 0.5) / BINS


def test_pixel_metrics_equal_sklearn_on_hand_made_scores():
    rng = np.random.default_rng(0)
    mask = rng.choice([0, 1, 255], size=(3, 20, 30), p=[0.8, 0.15, 0.05])
    scores = _on_bin_centres(np.clip(rng.normal(0.35 + 0.3 * (mask == 1), 0.2), 0, 1))
    scores[0, :2] = 0.5005  # many ties
    metric = AnomalyMetrics(["s"], num_rules=0, num_classes=3)
    metric.update(torch.from_numpy(scores)[None].float(), torch.from_numpy(mask))
    got = metric.compute()["scores"]["s"]
    valid = mask != 255
    y, s = (mask[valid] == 1).astype(int), scores[valid].astype(np.float32)
    assert got["auroc"] == pytest.approx(roc_auc_score(y, s), abs=1e-12)
    assert got["ap"] == pytest.approx(average_precision_score(y, s), abs=1e-12)
    fpr, tpr, _ = roc_curve(y, s)
    assert got["fpr95"] == pytest.approx(fpr[np.searchsorted(tpr, 0.95)], abs=1e-12)


def _components(binary: np.ndarray) -> list[set[tuple[int, int]]]:
    """8-connected components by a plain flood fill."""
    seen, out = set(), []
    for start in zip(*np.nonzero(binary), strict=True):
        if start in seen:
            continue
        stack, part = [start], set()
        seen.add(start)
        while stack:
            y, x = stack.pop()
            part.add((y, x))
            for dy in (-1, 0, 1):
                for dx in (-1, 0, 1):
                    n = (y + dy, x + dx)
                    inside = 0 <= n[0] < binary.shape[0] and 0 <= n[1] < binary.shape[1]
                    if inside and binary[n] and n not in seen:
                        seen.add(n)
                        stack.append(n)
        out.append(part)
    return out


def _reference(prediction: np.ndarray, mask: np.ndarray) -> tuple[list[float], list[float]]:
    """sIoU per ground-truth component and PPV per predicted one, from the definitions."""
    gts = _components(mask == 1)
    preds = _components(prediction & (mask != 255))
    siou = []
    for k in gts:
        hit = set().union(*[p for p in preds if p & k])
        others = set().union(*[g for g in gts if g is not k])
        siou.append(len(k & hit) / len((k | hit) - others))
    anomaly = set().union(*gts)
    ppv = [len(p & anomaly) / len(p) for p in preds]
    return siou, ppv


def test_components_on_hand_built_masks_with_known_answers():
    mask = np.zeros((8, 12), np.int64)
    mask[1:4, 1:4] = 1  # a 3 x 3 object ...
    mask[1:4, 8:11] = 1  # ... and another
    mask[6, :] = 255
    prediction = np.zeros((8, 12), bool)
    prediction[1:4, 1:3] = True  # 6 of the first object's 9 pixels
    prediction[2, 7:10] = True  # touches the second object: 2 of its pixels, 1 outside
    prediction[6:8, 5] = True  # a void pixel (removed) and one false pixel below it
    counts = component_counts(prediction, mask)
    siou, ppv = _reference(prediction, mask)
    assert siou == pytest.approx([6 / 9, 2 / 10]) and sorted(ppv) == pytest.approx([0, 2 / 3, 1])
    assert counts[-1].tolist() == pytest.approx([sum(siou), 2, sum(ppv), 3])
    for t, tau in enumerate(TAUS):
        tp = sum(v > tau for v in siou)
        assert counts[t, :3].tolist() == [tp, 2 - tp, sum(v <= tau for v in ppv)]


def test_split_and_merged_predictions_against_the_flood_fill():
    rng = np.random.default_rng(3)
    for _ in range(20):
        mask = np.where(rng.random((12, 16)) < 0.25, 1, 0)
        mask[rng.random((12, 16)) < 0.05] = 255
        prediction = rng.random((12, 16)) < 0.3
        counts = component_counts(prediction, mask)
        siou, ppv = _reference(prediction, mask)
        assert counts[-1].tolist() == pytest.approx([sum(siou), len(siou), sum(ppv), len(ppv)])
        metrics = component_metrics(counts)
        f1 = []
        for tau in TAUS:
            tp, fn = sum(v > tau for v in siou), sum(v <= tau for v in siou)
            fp = sum(v <= tau for v in ppv)
            f1.append(2 * tp / (2 * tp + fn + fp) if 2 * tp + fn + fp else np.nan)
        assert metrics["mean_f1"] == pytest.approx(np.mean(f1), nan_ok=True)


def test_the_metric_adds_up_across_batches_and_counts_the_rules_decisions():
    rng = np.random.default_rng(1)
    mask = torch.from_numpy(rng.choice([0, 1, 255], size=(4, 10, 12), p=[0.7, 0.25, 0.05]))
    scores = torch.rand(2, 4, 10, 12, generator=torch.Generator().manual_seed(0))
    preds = torch.randint(0, 3, (2, 4, 10, 12), generator=torch.Generator().manual_seed(1))
    preds[1, :, :2] = 255  # deferred
    whole = AnomalyMetrics(["a", "b"], num_rules=2, num_classes=3)
    whole.update(scores, mask, preds)
    parts = AnomalyMetrics(["a", "b"], num_rules=2, num_classes=3)
    for half in (slice(0, 1), slice(1, 4)):
        parts.update(scores[:, half], mask[half], preds[:, half])
    a, b = whole.compute(), parts.compute()
    assert a["scores"] == b["scores"] and torch.equal(a["decided"], b["decided"])
    for r in range(2):
        on = preds[r][mask == 1]
        want = [int((on == c).sum()) for c in range(3)] + [int((on == 255).sum())]
        assert a["decided"][r].tolist() == want


def test_evaluate_with_anomalies_end_to_end(tiny_run, tmp_path):
    """results.json's anomaly section: the rules' decisions count every unknown object's pixel,
    and max-softmax's pixel AUROC is sklearn's on the saved probabilities (up to the bins)."""
    ckpt = find_checkpoint(None, runs_dir=tiny_run[2])
    out = tmp_path / "eval"
    evaluate_main(
        ["--ckpt_path", str(ckpt), "--cost", "robotistic", "altruistic", "--anomalies",
         "--limit", "2", "--num_examples", "1", "--no-progress", "--save-probs",
         "--output_dir", str(out)]
    )  # fmt: skip
    found = json.loads((out / "results.json").read_text())["anomalies"]
    settings = data_settings(load_costseg_checkpoint(ckpt).data_config)
    scenes = settings.dataset("val", anomalies=True)
    masks = [scenes.with_anomalies(i)[3] for i in range(2)]
    anomaly_pixels = sum(int((m == 1).sum()) for m in masks)
    for rule in ("robotistic", "altruistic"):
        assert sum(found["decided_pixels"][rule]) == anomaly_pixels
    assert set(found["scores"]) == {
        "max_softmax",
        "entropy",
        *(f"cost_margin/{r}" for r in ("robotistic", "altruistic")),
    }
    scores, labels = [], []
    for i, mask in enumerate(masks):
        probs = load_probs(find_probs_file(out / "probs", f"val_{i:06d}"))
        valid = mask != 255
        scores.append((1 - probs.float().amax(0))[valid].numpy())
        labels.append((mask[valid] == 1).numpy())
    want = roc_auc_score(np.concatenate(labels), np.concatenate(scores))
    assert found["scores"]["max_softmax"]["auroc"] == pytest.approx(want, abs=2e-3)
    assert "## Unknown objects" in (out / "table.md").read_text()
    events = EventAccumulator(str(out)).Reload()
    logged = events.Scalars("evaluation/anomaly/auroc/max_softmax")
    assert logged[0].value == pytest.approx(found["scores"]["max_softmax"]["auroc"])
    assert (out / "figures" / "anomaly_maps_0.png").is_file()
    assert "evaluation/anomaly_maps_0" in events.Tags()["images"]


def test_anomalies_need_the_procedural_scenes(tiny_run, tmp_path, cityscapes_root, capsys):
    ckpt = str(find_checkpoint(None, runs_dir=tiny_run[2]))
    with pytest.raises(SystemExit):
        evaluate_main(["--ckpt_path", ckpt, "--anomalies", "--data_root", str(cityscapes_root),
                       "--no-progress", "--output_dir", str(tmp_path / "out")])  # fmt: skip
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--anomalies needs the procedural scenes" in err[0]
