"""RoIPrecisionRecall and SegmentErrors: batching, K rules at once, torchmetrics agreement."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from torchmetrics.classification import MulticlassConfusionMatrix, MulticlassJaccardIndex

from costseg.metrics import RoIPrecisionRecall, SegmentErrors
from costseg.metrics.functional import roi_confusion, segment_errors

IGNORE = 255


def make_batch(seed: int, b: int = 6, k: int = 4, h: int = 12, w: int = 16, n: int = 19):
    """Blobby labels, K rules that mostly agree (some identical), ignore pixels, RoI ids 0..4."""
    g = torch.Generator().manual_seed(seed)

    def blobs(*lead: int, classes: int) -> torch.Tensor:
        coarse = torch.rand(*lead, classes, h // 4, w // 4, generator=g)
        return F.interpolate(coarse, (h, w), mode="bilinear").argmax(-3)

    target = blobs(b, classes=n)
    target[torch.rand(b, h, w, generator=g) < 0.1] = IGNORE
    base = blobs(b, classes=n)
    preds = base.unsqueeze(1).repeat(1, k, 1, 1)
    flip = torch.rand(b, k, h, w, generator=g) < 0.05
    preds[flip] = torch.randint(0, n, (int(flip.sum()),), generator=g)
    preds[:, -1] = preds[:, 0]  # two rules with identical decisions (when k > 1)
    roi = blobs(1, classes=5)[0]
    return preds, target, roi


def assert_same(a: dict, b: dict) -> None:
    assert a.keys() == b.keys()
    for key in a:
        assert a[key].shape == b[key].shape, key
        torch.testing.assert_close(a[key], b[key], rtol=0, atol=0, equal_nan=True, msg=key)


@pytest.mark.parametrize("metric_cls", [RoIPrecisionRecall, SegmentErrors])
def test_one_batch_equals_many_batches(metric_cls: type) -> None:
    preds, target, roi = make_batch(0)
    kwargs = {"num_rules": 4} | ({"classes": (3, 7)} if metric_cls is SegmentErrors else {})
    one, many = metric_cls(**kwargs), metric_cls(**kwargs)
    one.update(preds, target, roi)
    for i in range(len(preds)):
        many.update(preds[i : i + 1], target[i : i + 1], roi)
    assert_same(one.compute(), many.compute())


@pytest.mark.parametrize("metric_cls", [RoIPrecisionRecall, SegmentErrors])
def test_k_rules_at_once_equal_k_separate_metrics(metric_cls: type) -> None:
    preds, target, roi = make_batch(1)
    extra = {"classes": (3, 7), "heatmap_size": (6, 8)} if metric_cls is SegmentErrors else {}
    joint = metric_cls(num_rules=4, **extra)
    joint.update(preds, target, roi)
    together = joint.compute()
    for k in range(4):
        single = metric_cls(num_rules=1, **extra)
        single.update(preds[:, k], target, roi)
        assert_same({key: v[k : k + 1] for key, v in together.items()}, single.compute())


def test_roi_precision_recall_matches_torchmetrics() -> None:
    preds, target, roi = make_batch(2, n=19)
    preds[preds == 5] = 6  # class 5 never predicted; classes 17, 18 absent from both
    target[target == 5] = IGNORE
    preds[preds >= 17] = 0
    target[target >= 17] = 0
    metric = RoIPrecisionRecall(num_rules=4)
    metric.update(preds, target, roi)
    out = metric.compute()
    for k in range(4):
        jaccard = MulticlassJaccardIndex(num_classes=19, ignore_index=IGNORE, average="macro")
        confmat = MulticlassConfusionMatrix(num_classes=19, ignore_index=IGNORE)
        assert torch.equal(out["confmat"][k, 0], confmat(preds[:, k], target))
        torch.testing.assert_close(out["miou"][k], jaccard(preds[:, k], target).double())
        # Per RoI: torchmetrics on that RoI's pixels only.
        for r in range(1, 5):
            inside = roi.expand_as(target) == r
            masked = torch.where(inside, target, IGNORE)
            assert torch.equal(out["confmat"][k, r], confmat(preds[:, k], masked))
    assert out["iou"][:, 17:].isnan().all() and not out["iou"][:, :5].isnan().any()
    assert out["miou"].shape == (4,) and out["precision"].shape == (4, 5, 19)


def test_roi_precision_recall_values_and_nan() -> None:
    metric = RoIPrecisionRecall(num_classes=3, num_rois=2)
    preds = torch.tensor([[[0, 1], [1, 2]]])
    target = torch.tensor([[[0, 1], [0, IGNORE]]])
    metric.update(preds, target, roi=torch.tensor([[1, 1], [1, 0]]))
    out = metric.compute()
    nan = float("nan")
    np.testing.assert_equal(out["precision"][0].tolist(), [[1, 0.5, nan], [1, 0.5, nan], [nan] * 3])
    np.testing.assert_equal(out["recall"][0].tolist(), [[0.5, 1, nan], [0.5, 1, nan], [nan] * 3])
    np.testing.assert_allclose(out["miou"].tolist(), [0.5])  # class 2: only on an ignored pixel
    assert out["miou"].shape == (1,)  # not squeezed to 0-d by torchmetrics
    empty = RoIPrecisionRecall(num_classes=3)
    empty.update(preds, torch.full_like(target, IGNORE))
    assert empty.compute()["miou"].isnan().all()


def test_segment_errors_match_functional_per_image() -> None:
    preds, target, roi = make_batch(3)
    classes = (3, 7, 11)
    metric = SegmentErrors(classes=classes, num_rules=4, num_rois=4)
    metric.update(preds, target, roi)
    out = metric.compute()
    keys = {"fp": "fp_roi", "fn": "fn_roi", "n_pred": "n_pred_roi", "n_gt": "n_gt_roi"}
    expected = {key: torch.zeros(4, 3, 5, dtype=torch.long) for key in keys}
    fp_map = torch.zeros(4, 3, 12, 16, dtype=torch.float64)
    for k in range(4):
        for c, cls in enumerate(classes):
            for b in range(len(preds)):
                seg = segment_errors(preds[b, k], target[b], cls, IGNORE, roi, num_rois=4)
                for key, roi_key in keys.items():
                    expected[key][k, c] += seg[roi_key]
                fp_map[k, c] += seg["fp_mask"]
    assert expected["fp"][..., 0].sum() > 10 and expected["fn"][..., 0].sum() > 10
    assert_same({key: out[key] for key in keys}, expected)
    torch.testing.assert_close(out["fp_map"], fp_map / len(preds), rtol=0, atol=0)
    rate = expected["fp"].double() / expected["n_pred"]
    torch.testing.assert_close(out["fp_rate"], rate, equal_nan=True)


def test_segment_errors_heatmap_is_area_resampled() -> None:
    preds, target, roi = make_batch(4, k=1)
    full, small = SegmentErrors(classes=(3,)), SegmentErrors(classes=(3,), heatmap_size=(3, 4))
    for metric in (full, small):
        metric.update(preds[:, 0], target, roi)
    expected = full.compute()["fp_map"].reshape(1, 1, 3, 4, 4, 4).mean((3, 5))
    torch.testing.assert_close(small.compute()["fp_map"], expected)
    off = SegmentErrors(classes=(3,), heatmap_size=(0, 0))
    off.update(preds[:, 0], target, roi)
    assert off.compute()["fp_map"].shape == (1, 1, 0, 0)
    assert torch.equal(off.compute()["fp"], full.compute()["fp"])


def test_segment_errors_rates_nan_and_shapes() -> None:
    metric = SegmentErrors(classes=(1,), num_rois=0)
    metric.update(torch.zeros(1, 4, 4, dtype=torch.long), torch.zeros(1, 4, 4, dtype=torch.long))
    out = metric.compute()
    assert out["fp"].shape == (1, 1, 1) and out["fp_map"].shape == (1, 1, 4, 4)
    assert out["fp_rate"].isnan().all() and out["fn_rate"].isnan().all()
    assert (out["fp_map"] == 0).all()


def test_forward_merge_and_reset_keep_sums() -> None:
    preds, target, roi = make_batch(5)
    reference = SegmentErrors(classes=(3,), num_rules=4)
    reference.update(preds, target, roi)
    stepped, other = SegmentErrors(classes=(3,), num_rules=4), SegmentErrors((3,), num_rules=4)
    first = stepped(preds[:2], target[:2], roi)  # forward: batch value, state accumulates
    other.update(preds[2:], target[2:], roi)
    stepped.merge_state(other)
    assert first["fp_map"].shape == (4, 1, 12, 16)
    assert_same(stepped.compute(), reference.compute())
    stepped.reset()
    stepped.update(preds, target, roi)
    assert_same(stepped.compute(), reference.compute())


def test_metrics_reject_bad_input() -> None:
    preds, target, roi = make_batch(6)
    with pytest.raises(ValueError, match=r"\(B, 3, H, W\)"):
        RoIPrecisionRecall(num_rules=3).update(preds, target, roi)
    with pytest.raises(ValueError, match=r"\(B, 4, H, W\)"):
        SegmentErrors(num_rules=4).update(preds[:, 0], target, roi)
    with pytest.raises(ValueError, match="heatmap_size"):
        SegmentErrors(heatmap_size=(0, 5))
    with pytest.raises(ValueError, match="class ids"):
        SegmentErrors(classes=(255,))
    assert roi_confusion(preds, target, roi).shape == (4, 5, 19, 19)


def test_images_of_another_size_land_on_the_same_canvas() -> None:
    """A 2x nearest-upsampled copy of a batch adds exactly the same FP/FN maps (area pooling)."""
    preds, target, roi = make_batch(6)
    big = [t.repeat_interleave(2, -1).repeat_interleave(2, -2) for t in (preds, target, roi)]
    once = SegmentErrors(num_rules=4)
    once.update(preds, target, roi)
    both = SegmentErrors(num_rules=4)
    both.update(preds, target, roi)
    both.update(*big)
    expected, got = once.compute(), both.compute()
    assert got["fp_map"].shape == expected["fp_map"].shape
    assert torch.allclose(got["fp_map"], expected["fp_map"])
    assert torch.allclose(got["fn_map"], expected["fn_map"])


def test_metrics_work_in_a_metric_collection() -> None:
    """One update of a torchmetrics MetricCollection feeds every metric; batches, merging and
    cloning behave as for the metrics alone."""
    from torchmetrics import MetricCollection

    from costseg.metrics.scoring import GroupMetrics
    from costseg.rules import parse_rules, rules_group

    preds, target, roi = make_batch(7)
    collection = MetricCollection(
        {
            "pixels": RoIPrecisionRecall(num_rules=4),
            "segments": SegmentErrors(classes=(3, 5), num_rules=4),
        },
        compute_groups=False,
    )
    pixels, segments = RoIPrecisionRecall(num_rules=4), SegmentErrors((3, 5), num_rules=4)
    for metric in (pixels, segments):
        metric.update(preds, target, roi)
    first = collection(preds[:2], target[:2], roi)  # forward: the first batch alone
    collection.update(preds[2:], target[2:], roi)
    out = collection.compute()  # the results' keys are distinct, so they stay unprefixed
    assert_same({k: out[k] for k in pixels.compute()}, pixels.compute())
    assert_same({k: out[k] for k in segments.compute()}, segments.compute())
    assert first["confmat"][:, 0].sum() == (target[:2] != IGNORE).sum() * 4  # RoI 0: the image
    # The group wrapper of evaluation and validation fits in a collection too.
    group = rules_group(parse_rules(["robotistic", "altruistic", "egoistic", "ml"]))
    wrapped = MetricCollection({"named": GroupMetrics(group, 19, segment_classes=(3, 5))})
    wrapped.update(preds, target, roi)
    nested = wrapped["named"].compute()
    assert_same(nested["pixels"], pixels.compute())
    assert_same(nested["segments"], segments.compute())
    wrapped.reset()
    assert wrapped["named"].pixels.confmat.sum() == 0
