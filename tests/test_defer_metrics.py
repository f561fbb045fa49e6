"""The metrics of deferral (docs/definitions.md §14) against brute-force loops: coverage, deferred
rate, selective and handled recall, recall, precision and IoU over pixels; instances missed with
deferral over instances; segments on hand-made maps with deferred pixels; per-image counts and
targets; batches and merged states (the sums DDP merges) equal one pass."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy import ndimage
from test_instances import CLASSES, predictions, roi_blocks, scenes

from costseg.decision.label_maps import DEFERRED as D
from costseg.metrics import InstanceMisses, RoIPrecisionRecall, SegmentErrors
from costseg.metrics.functional import iou_from_confusion, precision_recall, segment_errors
from costseg.metrics.functional.roi import COMPILED_MIN_RULES
from costseg.metrics.per_image import per_image_counts, per_image_loss
from costseg.metrics.selection import choose, metric_values, parse_target, risk_level

N, R = 4, 2
DEFER_METRICS = ("coverage", "selective_recall", "handled_recall")


def random_case(seed: int, k: int = 3, b: int = 2, h: int = 6, w: int = 8):
    """(B, K, H, W) labels, rule j deferring a share j / K of the pixels; (B, H, W) targets with
    ignored pixels; an (H, W) RoI map."""
    gen = torch.Generator().manual_seed(seed)
    preds = torch.randint(0, N, (b, k, h, w), generator=gen)
    share = (torch.arange(k) / k).view(1, k, 1, 1)
    preds[torch.rand(b, k, h, w, generator=gen) < share] = D
    target = torch.randint(0, N, (b, h, w), generator=gen)
    target[torch.rand(b, h, w, generator=gen) < 0.15] = 255
    return preds, target, torch.randint(0, R + 1, (h, w), generator=gen)


def brute_pixels(preds, target, roi) -> dict[str, np.ndarray]:
    """(K, R+1, N) counts, pixel by pixel: TP, GT (every valid pixel of the class), deferred
    (valid pixels of the class deferred), predicted (pixels labelled the class)."""
    b, k, h, w = preds.shape
    out = {key: np.zeros((k, R + 1, N), np.int64) for key in ("tp", "gt", "d", "pred")}
    for i, j, y, x in np.ndindex(b, k, h, w):
        t, p, r = int(target[i, y, x]), int(preds[i, j, y, x]), int(roi[y, x])
        if t == 255:
            continue
        for region in {0, r}:
            out["gt"][j, region, t] += 1
            out["d"][j, region, t] += p == D
            if p != D:
                out["pred"][j, region, p] += 1
                out["tp"][j, region, t] += p == t
    return out


def ratio(a: float, b: float) -> float:
    return a / b if b else math.nan


def expected_pixels(c: dict[str, np.ndarray]) -> dict[str, torch.Tensor]:
    tp, gt, d, pred = (c[key].astype(float) for key in ("tp", "gt", "d", "pred"))
    f = np.vectorize(ratio)
    iou = f(tp[:, 0], gt[:, 0] + pred[:, 0] - tp[:, 0])
    out = {
        "recall": f(tp, gt),
        "precision": f(tp, pred),  # over the pixels labelled c: none of them is deferred
        "coverage": f(gt - d, gt),
        "selective_recall": f(tp, gt - d),
        "handled_recall": f(tp + d, gt),
        "deferred_rate": f(d.sum(-1), gt.sum(-1)),
        "iou": iou,
        "deferred": c["d"],
    }
    return {key: torch.from_numpy(np.asarray(v)) for key, v in out.items()} | {
        "miou": torch.tensor([np.nanmean(row) for row in iou])
    }


@pytest.mark.parametrize("dtype", [torch.int64, torch.uint8])
@pytest.mark.parametrize("k", [3, COMPILED_MIN_RULES + 1])  # tensor counts, compiled counts
@pytest.mark.parametrize("seed", range(2))
def test_pixel_metrics_equal_the_brute_force_loop(seed: int, k: int, dtype) -> None:
    preds, target, roi = random_case(seed, k)
    metric = RoIPrecisionRecall(N, k, R)
    metric.update(preds.to(dtype), target, roi)
    got = metric.compute()
    expected = expected_pixels(brute_pixels(preds, target, roi))
    for key, want in expected.items():
        exact = 1e-12 if key == "miou" else 0
        torch.testing.assert_close(got[key], want, rtol=exact, atol=0, equal_nan=True, msg=key)
    assert int(got["confmat"][0, 0].sum()) == int((target != 255).sum())  # rule 0 never defers
    assert 0 < float(got["deferred_rate"][-1, 0]) < 1  # some deferred, not all


def test_without_deferral_nothing_changes() -> None:
    preds, target, roi = random_case(0, k=1)  # rule 0 defers nothing
    metric = RoIPrecisionRecall(N, 1, R)
    metric.update(preds, target, roi)
    out = metric.compute()
    cm = out["confmat"]
    precision, recall = precision_recall(cm)  # the formulas without deferral
    same = {"precision": precision, "recall": recall, "iou": iou_from_confusion(cm[:, 0])}
    for key, want in same.items():
        torch.testing.assert_close(out[key], want, rtol=0, atol=0, equal_nan=True, msg=key)
    assert int(out["deferred"].abs().sum()) == 0 and torch.all(out["deferred_rate"] == 0)
    present = cm.sum(-1) > 0
    assert torch.all(out["coverage"][present] == 1)
    assert torch.equal(out["handled_recall"][present], out["recall"][present])


@pytest.mark.parametrize("k", [2, COMPILED_MIN_RULES])
def test_labels_that_are_neither_class_nor_deferred_are_refused(k: int) -> None:
    preds, target, roi = random_case(0, k)
    preds[0, 1, 0, 0] = 200
    with pytest.raises(ValueError, match=r"expected preds in \[0, 4\) or 255"):
        RoIPrecisionRecall(N, k, R).update(preds, target, roi)


def test_batches_and_merged_states_equal_one_pass() -> None:
    preds, target, roi = random_case(3, k=4, b=4)
    one = RoIPrecisionRecall(N, 4, R)
    one.update(preds, target, roi)
    first, second = RoIPrecisionRecall(N, 4, R), RoIPrecisionRecall(N, 4, R)
    first.update(preds[:1], target[:1], roi)  # one process: two batches
    first.update(preds[1:2], target[1:2], roi)
    second.update(preds[2:], target[2:], roi)  # another process
    first.merge_state(second)  # the sum DDP takes of every state
    a, b = one.compute(), first.compute()
    for key in a:
        torch.testing.assert_close(a[key], b[key], rtol=0, atol=0, equal_nan=True, msg=key)


def test_a_deferred_instance_is_not_missed() -> None:
    labels, ids, _ = scenes()
    preds, roi = predictions(labels), roi_blocks()
    gen = torch.Generator().manual_seed(2)
    for j, share in enumerate((0.5, 0.97, 0.999)):
        preds[:, j][torch.rand(labels.shape, generator=gen) < share] = D
    metric = InstanceMisses(CLASSES, 3)
    metric.update(preds, labels, ids, roi)
    got = metric.compute()["missed_instances"]
    expected = torch.zeros_like(got)
    for i in range(len(labels)):  # instance by instance
        for value in ids[i].unique().tolist():
            cls = {24: CLASSES[0], 26: CLASSES[1]}.get(value // 1000)
            pixels = (ids[i] == value) & (labels[i] != 255)
            if value < 1000 or cls is None or not pixels.any():
                continue
            votes = torch.bincount(roi[pixels], minlength=5)
            for j in range(3):
                found = preds[i, j][pixels]
                if not ((found == cls) | (found == D)).any():
                    for r in {0, int(votes.argmax())}:
                        expected[j, CLASSES.index(cls), r] += 1
    assert torch.equal(got, expected)
    person = torch.tensor([[[24000, 24000, 24001, 24001]]])
    target = torch.full((1, 1, 4), CLASSES[0])
    alone = InstanceMisses((CLASSES[0],), 1, num_rois=0)
    alone.update(torch.tensor([[[D, D, 0, 0]]]), target, person)  # deferred; predicted road
    assert alone.compute()["missed_instances"].tolist() == [[[1]]]


# A hand-made map of class 1 (4 x 6 pixels, D = deferred): the ground-truth segment at the left
# is all deferred (a false negative), the one at the right half predicted 1 (found); the
# prediction's 1 in the middle is a false positive; the deferred pixels at the bottom belong to
# no segment. Rule 1 answers 1 wherever rule 0 defers.
TARGET = [[1, 1, 0, 0, 0, 1], [1, 1, 0, 0, 0, 1], [0, 0, 0, 0, 0, 0], [0, 0, 0, 0, 0, 0]]
RULE = [[D, D, 0, 0, 0, D], [D, D, 0, 0, 0, 1], [0, 0, 0, 1, 0, 0], [D, D, 0, 0, 0, 0]]
HAND = {"fp": [1, 2], "fn": [1, 0], "n_pred": [2, 4], "n_gt": [2, 2]}  # rule 0, rule 1


@pytest.mark.parametrize("path", ["definition", "with maps", "compiled runs", "uint8 bits"])
def test_segments_treat_deferred_pixels_as_neither_class(path: str) -> None:
    rule = torch.tensor(RULE)
    rules = torch.stack([rule, torch.where(rule == D, 1, rule)])[None]  # (1, 2, 4, 6)
    target = torch.tensor(TARGET)[None]
    if path == "definition":
        got = [segment_errors(rules[0, j], target[0], cls=1) for j in range(2)]
        counts = {key: [g[key] for g in got] for key in HAND}
        left = torch.zeros(4, 6, dtype=torch.bool)
        left[:2, :2] = True
        assert torch.equal(got[0]["fn_mask"], left)
        assert not got[0]["fp_mask"][rule == D].any()
    else:
        size = (4, 6) if path == "with maps" else (0, 0)
        metric = SegmentErrors(classes=(1,), num_rules=2, num_rois=0, heatmap_size=size)
        metric.update(rules.to(torch.uint8 if path == "uint8 bits" else torch.long), target)
        counts = {key: metric.compute()[key][:, 0, 0].tolist() for key in HAND}
    assert counts == HAND


def test_random_segments_with_deferral_equal_scipy_labels() -> None:
    preds, target, _ = random_case(5, k=3, b=2, h=8, w=8)
    eight = np.ones((3, 3), bool)
    for maps in ((8, 8), (0, 0)):
        metric = SegmentErrors(classes=(1, 2), num_rules=3, num_rois=0, heatmap_size=maps)
        metric.update(preds, target)
        out = metric.compute()
        for c, cls in enumerate((1, 2)):
            for j in range(3):
                fp = fn = 0
                for i in range(2):
                    p, t = preds[i, j].numpy(), target[i].numpy()
                    mine, truth = (p == cls) & (t != 255), t == cls
                    for own, other, is_fp in ((mine, truth, True), (truth, p == cls, False)):
                        labels, count = ndimage.label(own, structure=eight)
                        missed = sum(not other[labels == s].any() for s in range(1, count + 1))
                        fp, fn = (fp + missed, fn) if is_fp else (fp, fn + missed)
                assert (int(out["fp"][j, c, 0]), int(out["fn"][j, c, 0])) == (fp, fn)


@pytest.mark.parametrize("metric", ["recall", "precision", *DEFER_METRICS])
def test_per_image_counts_sum_to_the_pooled_metric(metric: str) -> None:
    preds, target, roi = random_case(7, k=4, b=3)
    pooled = RoIPrecisionRecall(N, 4, R)
    pooled.update(preds, target, roi)
    out = pooled.compute()
    brute = [brute_pixels(preds[i : i + 1], target[i : i + 1], roi) for i in range(3)]
    for cls in range(N):
        for roi_id in range(R + 1):
            counts = per_image_counts(preds, target, roi, cls, roi_id, metric, num_rois=R)
            for i, c in enumerate(brute):  # each image against its own brute-force counts
                tp, gt, d, pred = (c[key][:, roi_id, cls] for key in ("tp", "gt", "d", "pred"))
                parts = {
                    "recall": (tp, gt),
                    "precision": (tp, pred),
                    "coverage": (gt - d, gt),
                    "selective_recall": (tp, gt - d),
                    "handled_recall": (tp + d, gt),
                }
                assert counts[i].tolist() == np.stack(parts[metric], -1).tolist()
            part, whole = counts.sum(0).double().unbind(-1)
            torch.testing.assert_close(
                part / whole, out[metric][:, roi_id, cls], rtol=0, atol=0, equal_nan=True
            )
    loss = per_image_loss(counts, metric)
    torch.testing.assert_close(loss, 1 - counts[..., 0].double() / counts[..., 1], equal_nan=True)


def test_targets_name_the_metrics_of_deferral() -> None:
    target = parse_target("person:roi1:handled_recall>=0.99")
    assert target.metric == "handled_recall" and math.isclose(risk_level(target), 0.01)
    assert parse_target("car:roi2:coverage>0.5").metric == "coverage"
    with pytest.raises(ValueError, match="rate in"):
        parse_target("person:roi1:coverage>=1.5")
    with pytest.raises(ValueError, match="coverage, selective_recall, handled_recall"):
        risk_level(parse_target("person:roi1:selective_recall<=0.5"))
    preds, target_map, roi = random_case(1, k=3)
    metric = RoIPrecisionRecall(19, 3, R)
    metric.update(preds, target_map, roi)
    pixels = metric.compute()
    values = metric_values(pixels, {}, parse_target("road:roi1:coverage>=0.5"), [])
    assert torch.equal(values, pixels["coverage"][:, 1, 0])
    best = choose(pixels, {}, "road:roi1:coverage>=0.5", "road:roi1:selective_recall", [])
    assert best.points and all(values[p] >= 0.5 for p in best.points)
