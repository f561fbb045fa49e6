"""Per-image counts and losses of a guarantee target: against brute force (python loops and
scipy.ndimage.label), and summed over images against the pooled metrics."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy import ndimage

from costseg.metrics import RoIPrecisionRecall, SegmentErrors
from costseg.metrics.per_image import per_image_counts, per_image_loss

NUM_ROIS = 3
CLS = 1
EIGHT = np.ones((3, 3), dtype=bool)


def random_batch(seed: int, b: int = 3, k: int = 4, h: int = 10, w: int = 13, roi_3d=False):
    """Blobby (B, K, H, W) uint8 preds, (B, H, W) targets with ignored pixels, a RoI map."""
    gen = torch.Generator().manual_seed(seed)

    def blobs(*shape: int) -> torch.Tensor:
        coarse = torch.randint(0, 3, (*shape[:-2], shape[-2] // 2 + 1, shape[-1] // 2 + 1),
                               generator=gen)  # fmt: skip
        up = coarse.repeat_interleave(2, -2).repeat_interleave(2, -1)[..., : shape[-2], : shape[-1]]
        noise = torch.randint(0, 3, shape, generator=gen)
        return torch.where(torch.rand(shape, generator=gen) < 0.2, noise, up)

    preds = blobs(b, k, h, w).to(torch.uint8)
    target = blobs(b, h, w)
    target[torch.rand(b, h, w, generator=gen) < 0.1] = 255
    roi = torch.randint(0, NUM_ROIS + 1, (b, h, w) if roi_3d else (h, w), generator=gen)
    return preds, target, roi


def brute_pixels(preds, target, roi, roi_id: int, metric: str) -> np.ndarray:
    b, k, h, w = preds.shape
    roi = roi.expand_as(target)
    out = np.zeros((b, k, 2), dtype=np.int64)
    for i in range(b):
        for j in range(k):
            for y in range(h):
                for x in range(w):
                    t, p = int(target[i, y, x]), int(preds[i, j, y, x])
                    if t == 255 or (roi_id and int(roi[i, y, x]) != roi_id):
                        continue
                    out[i, j, 0] += t == CLS and p == CLS
                    out[i, j, 1] += (t == CLS) if metric == "recall" else (p == CLS)
    return out


def owner(labels: np.ndarray, comp: int, roi: np.ndarray) -> int:
    ids = roi[labels == comp].tolist()
    counts = [ids.count(r) for r in range(NUM_ROIS + 1)]
    return counts.index(max(counts))  # ties: lowest id


def brute_segments(preds, target, roi, roi_id: int, metric: str) -> np.ndarray:
    b, k = preds.shape[:2]
    roi = roi.expand_as(target).numpy()
    out = np.zeros((b, k, 2), dtype=np.int64)
    for i in range(b):
        t = target[i].numpy()
        for j in range(k):
            p = preds[i, j].numpy()
            pred_mask, gt_mask = (p == CLS) & (t != 255), t == CLS
            own, other = (pred_mask, gt_mask) if metric == "fp_rate" else (gt_mask, p == CLS)
            labels, count = ndimage.label(own, structure=EIGHT)
            for comp in range(1, count + 1):
                if roi_id and owner(labels, comp, roi[i]) != roi_id:
                    continue
                out[i, j, 1] += 1
                out[i, j, 0] += not other[labels == comp].any()
    return out


@pytest.mark.parametrize("roi_3d", [False, True])
@pytest.mark.parametrize("metric", ["recall", "precision", "fn_rate", "fp_rate"])
def test_counts_match_brute_force(metric: str, roi_3d: bool) -> None:
    brute = brute_pixels if metric in ("recall", "precision") else brute_segments
    for seed in range(3):
        preds, target, roi = random_batch(seed, roi_3d=roi_3d)
        for roi_id in range(NUM_ROIS + 1):
            got = per_image_counts(preds, target, roi, CLS, roi_id, metric, num_rois=NUM_ROIS)
            assert got.dtype == torch.int64 and got.shape == (*preds.shape[:2], 2)
            np.testing.assert_array_equal(got.numpy(), brute(preds, target, roi, roi_id, metric))
        whole = per_image_counts(preds, target, None, CLS, 0, metric, num_rois=NUM_ROIS)
        np.testing.assert_array_equal(whole.numpy(), brute(preds, target, roi, 0, metric))


@pytest.mark.parametrize("seed", range(3))
def test_summed_counts_equal_pooled_metrics(seed: int) -> None:
    preds, target, roi = random_batch(seed, b=4, k=5, h=16, w=20)
    k = preds.shape[1]
    pixels = RoIPrecisionRecall(num_classes=3, num_rules=k, num_rois=NUM_ROIS)
    segments = SegmentErrors(classes=(CLS,), num_rules=k, num_rois=NUM_ROIS, heatmap_size=(0, 0))
    for b in range(len(target)):  # image by image, as an evaluation streams them
        pixels.update(preds[b : b + 1], target[b : b + 1], roi)
        segments.update(preds[b : b + 1], target[b : b + 1], roi)
    cm, seg = pixels.compute()["confmat"], segments.compute()
    tp = cm[:, :, CLS, CLS]
    pooled = {
        "recall": (tp, cm[:, :, CLS, :].sum(-1)),
        "precision": (tp, cm[:, :, :, CLS].sum(-1)),
        "fn_rate": (seg["fn"][:, 0], seg["n_gt"][:, 0]),
        "fp_rate": (seg["fp"][:, 0], seg["n_pred"][:, 0]),
    }
    for metric, (part, whole) in pooled.items():
        for roi_id in range(NUM_ROIS + 1):
            counts = per_image_counts(preds, target, roi, CLS, roi_id, metric, num_rois=NUM_ROIS)
            summed = counts.sum(0)
            assert summed[:, 0].tolist() == part[:, roi_id].tolist(), (metric, roi_id)
            assert summed[:, 1].tolist() == whole[:, roi_id].tolist(), (metric, roi_id)


def test_loss_values_and_undefined() -> None:
    counts = torch.tensor([[[3, 4], [0, 0], [0, 5]], [[2, 2], [1, 3], [0, 0]]])
    for metric in ("recall", "precision"):
        loss = per_image_loss(counts, metric)
        assert loss.dtype == torch.float64 and loss.shape == (2, 3)
        want = [[1 - 3 / 4, math.nan, 1.0], [0.0, 1 - 1 / 3, math.nan]]
        np.testing.assert_allclose(loss.numpy(), want)
    for metric in ("fn_rate", "fp_rate"):
        want = [[3 / 4, math.nan, 0.0], [1.0, 1 / 3, math.nan]]
        np.testing.assert_allclose(per_image_loss(counts.numpy(), metric).numpy(), want)


def test_loss_of_real_counts_lies_in_unit_interval() -> None:
    preds, target, roi = random_batch(7, b=5)
    for metric in ("recall", "precision", "fn_rate", "fp_rate"):
        counts = per_image_counts(preds, target, roi, CLS, 1, metric, num_rois=NUM_ROIS)
        loss = per_image_loss(counts, metric)
        defined = counts[..., 1] > 0
        assert bool((loss.isnan() == ~defined).all())
        assert bool(((loss[defined] >= 0) & (loss[defined] <= 1)).all())


def test_bad_inputs() -> None:
    preds, target, roi = random_batch(0)
    with pytest.raises(ValueError, match="metric must be one of"):
        per_image_counts(preds, target, roi, CLS, 1, "iou", num_rois=NUM_ROIS)
    with pytest.raises(ValueError, match="needs a RoI map"):
        per_image_counts(preds, target, None, CLS, 1, "recall", num_rois=NUM_ROIS)
    with pytest.raises(ValueError, match=r"roi_id in 0\.\.3"):
        per_image_counts(preds, target, roi, CLS, 4, "recall", num_rois=NUM_ROIS)
    with pytest.raises(ValueError, match=r"\(B, K, H, W\)"):
        per_image_counts(preds[:, 0], target, roi, CLS, 0, "recall", num_rois=NUM_ROIS)
    with pytest.raises(ValueError, match="cls"):
        per_image_counts(preds, target, roi, 255, 0, "fp_rate", num_rois=NUM_ROIS)
    with pytest.raises(ValueError, match="target"):
        per_image_counts(preds, target[:1], roi, CLS, 0, "recall", num_rois=NUM_ROIS)
    with pytest.raises(ValueError, match=r"\(n, K, 2\)"):
        per_image_loss(torch.zeros(3, 2), "recall")
    with pytest.raises(ValueError, match="numerator"):
        per_image_loss(torch.tensor([[[5, 3]]]), "fn_rate")
