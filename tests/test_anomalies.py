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
from costseg.metrics.functional.anomaly import BINS, component_counts, component_metrics
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


def _reference(
    prediction: np.ndarray, mask: np.ndarray, min_pred: float = 0, min_gt: float = 0
) -> tuple[list[float], list[float]]:
    """sIoU per ground-truth component and PPV per predicted one, from the definitions of §17:
    predicted components of fewer than ``min_pred`` non-void pixels dropped, ground-truth ones of
    fewer than ``min_gt`` pixels made void, then every component restricted to the non-void."""
    void = set(zip(*np.nonzero(mask == 255), strict=True))
    gts = _components(mask == 1)
    void = void.union(*[g for g in gts if len(g) < min_gt])
    gts = [g for g in gts if len(g) >= min_gt]
    preds = [p - void for p in _components(prediction & (mask != 255)) if len(p) >= min_pred]
    preds = [p for p in preds if p]
    siou = []
    for k in gts:
        hit = set().union(*[p for p in preds if p & k])
        others = set().union(*[g for g in gts if g is not k])
        siou.append(len(k & hit) / len((k | hit) - others))
    anomaly = set().union(*gts)
    ppv = [len(p & anomaly) / len(p) for p in preds]
    return siou, ppv


def _per_tau(siou: list[float], ppv: list[float]) -> list[list[int]]:
    """(TP, FN, FP) at each τ: TP when sIoU ≥ τ, FN otherwise, FP when PPV < τ."""
    taus = np.linspace(0.25, 0.75, 11)  # the benchmark's thresholds, floats as it makes them
    return [[sum(v >= t for v in siou), sum(v < t for v in siou), sum(v < t for v in ppv)]
            for t in taus]  # fmt: skip


def _hand_built() -> tuple[np.ndarray, np.ndarray]:
    """Objects A (9 px), B (2 px) and C (6 px); five predicted blobs (see the test)."""
    mask = np.zeros((10, 14), np.int64)
    mask[1:4, 1:4] = 1  # A
    mask[1, 8:10] = 1  # B
    mask[6:8, 8:11] = 1  # C
    mask[9, :] = 255
    prediction = np.zeros((10, 14), bool)
    prediction[1:4, 1:3] = True  # P1: 6 of A's pixels
    prediction[0:2, 8:10] = True  # P2: 4 pixels, 2 of them B's
    prediction[5:8, 8:10] = True  # P3: 6 pixels, 4 of them C's
    prediction[8:10, 0] = True  # P4: 1 pixel and 1 void one
    prediction[5, 4:7] = True  # P5: 3 pixels
    return prediction, mask


@pytest.mark.parametrize(
    ("min_sizes", "siou", "ppv"),
    [
        # sizes 4 and 3: B is void, P2 keeps its 4 pixels' size but only its 2 off B count;
        # P4 (1 pixel without the void) and P5 are dropped; sIoU(C) = 4 / (6 + 6 - 4)
        ((4, 3), [6 / 9, 4 / 8], [1, 0, 4 / 6]),
        # no sizes: B is met by P2 alone, sIoU 2 / (2 + 4 - 2); P4 and P5 are false positives
        ((0, 0), [6 / 9, 2 / 4, 4 / 8], [1, 2 / 4, 4 / 6, 0, 0]),
    ],
)
def test_components_on_hand_built_masks_with_known_answers(min_sizes, siou, ppv):
    prediction, mask = _hand_built()
    got_siou, got_ppv = _reference(prediction, mask, *min_sizes)
    assert sorted(got_siou) == pytest.approx(sorted(siou))
    assert sorted(got_ppv) == pytest.approx(sorted(ppv))
    counts = component_counts(prediction, mask, min_sizes)
    assert counts[-1].tolist() == pytest.approx([sum(siou), len(siou), sum(ppv), len(ppv)])
    assert counts[:-1, :3].tolist() == _per_tau(siou, ppv)
    if min_sizes == (4, 3):  # sIoU 0.5 is a true positive at τ = 0.5 (≥), not at 0.55
        assert counts[5, 0] == 2 and counts[6, 0] == 1
        f1 = (6 * 4 / 5 + 3 * 2 / 4 + 2 * 0) / 11  # F1 4/5 up to τ = 0.5, 2/4 to 0.65, then 0
        assert component_metrics(counts)["mean_f1"] == pytest.approx(f1)


def _blobs(rng: np.random.Generator, shape: tuple[int, int], count: int) -> np.ndarray:
    """A bool mask of ``count`` random rectangles and discs."""
    ys, xs = np.mgrid[: shape[0], : shape[1]]
    out = np.zeros(shape, bool)
    for _ in range(count):
        cy, cx = rng.integers(0, shape[0]), rng.integers(0, shape[1])
        r = rng.uniform(0.5, 4)
        if rng.random() < 0.5:
            out |= (ys - cy) ** 2 + (xs - cx) ** 2 <= r * r
        else:
            out |= (abs(ys - cy) <= r) & (abs(xs - cx) <= rng.uniform(0.5, 4))
    return out


@pytest.mark.parametrize("min_sizes", [(0, 0), (6, 5), (12.5, 2.5)])
def test_random_blob_scenes_against_the_flood_fill(min_sizes):
    rng = np.random.default_rng(3)
    for _ in range(25):
        mask = np.where(_blobs(rng, (20, 28), 5), 1, 0)
        mask[_blobs(rng, (20, 28), 2) & (rng.random((20, 28)) < 0.7)] = 255
        near = _blobs(rng, (20, 28), 4)  # predictions near the objects, and elsewhere
        prediction = np.where(mask == 1, rng.random((20, 28)) < 0.8, near)
        prediction |= rng.random((20, 28)) < 0.03
        counts = component_counts(prediction, mask, min_sizes)
        siou, ppv = _reference(prediction, mask, *min_sizes)
        assert counts[-1].tolist() == pytest.approx([sum(siou), len(siou), sum(ppv), len(ppv)])
        assert counts[:-1, :3].tolist() == _per_tau(siou, ppv)
        f1 = [2 * tp / (2 * tp + fn + fp) if tp + fn + fp else np.nan
              for tp, fn, fp in _per_tau(siou, ppv)]  # fmt: skip
        got = component_metrics(counts)["mean_f1"]
        assert got == pytest.approx(np.mean(f1), nan_ok=True)


def test_the_track_sizes_scale_with_the_image_area():
    """At 256 x 512 (1 / 16 of 1024 x 2048) the AnomalyTrack drops objects under 6.25 pixels and
    predictions under 31.25, the ObstacleTrack under 0.625 and 3.125."""
    mask = torch.zeros(1, 256, 512, dtype=torch.int64)
    mask[0, 10:20, 10:20] = 1  # 100 pixels
    mask[0, 100:102, 100:103] = 1  # 6 pixels: void for the AnomalyTrack
    scores = torch.zeros(1, 1, 256, 512)
    scores[0, 0, 10:20, 10:20] = 0.9
    scores[0, 0, 200:205, 300:306] = 0.9  # 30 false pixels: dropped by the AnomalyTrack
    found = {}
    for track in ("anomaly", "obstacle"):
        metric = AnomalyMetrics(["s"], num_rules=0, num_classes=3, track=track)
        metric.update(scores, mask)
        found[track] = metric.compute()["scores"]["s"]
    assert (found["anomaly"]["siou"], found["anomaly"]["ppv"]) == (1, 1)
    assert found["anomaly"]["mean_f1"] == 1
    assert (found["obstacle"]["siou"], found["obstacle"]["ppv"]) == (0.5, 0.5)
    assert found["obstacle"]["mean_f1"] == pytest.approx(2 / 4)  # TP, FN and FP 1 at every τ
    with pytest.raises(ValueError, match="unknown track"):
        AnomalyMetrics(["s"], num_rules=0, num_classes=3, track="road")


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


@pytest.mark.figures
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
