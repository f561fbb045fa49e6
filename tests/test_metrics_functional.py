"""costseg.metrics.functional against brute-force loops and hand-computed cases."""

from __future__ import annotations

from collections import Counter, deque

import hypothesis.extra.numpy as hnp
import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import ndimage

from costseg.metrics.functional import (
    iou_from_confusion,
    mean_iou,
    precision_recall,
    roi_confusion,
    roi_metrics,
    segment_errors,
)
from costseg.metrics.functional import roi as functional_roi

IGNORE = 255


def confusion_reference(preds, target, roi, n, num_rois):
    """(K, R+1, N, N) counts by visiting every pixel; preds (B, K, H, W), roi (B, H, W)."""
    b_, k_, h_, w_ = preds.shape
    cm = np.zeros((k_, num_rois + 1, n, n), dtype=np.int64)
    for k in range(k_):
        for b in range(b_):
            for y in range(h_):
                for x in range(w_):
                    t, p, r = int(target[b, y, x]), int(preds[b, k, y, x]), int(roi[b, y, x])
                    if t == IGNORE:
                        continue
                    cm[k, 0, t, p] += 1
                    if r > 0:
                        cm[k, r, t, p] += 1
    return cm


@pytest.mark.parametrize("seed", range(4))
@pytest.mark.parametrize("roi_kind", ["none", "shared", "per_image"])
@pytest.mark.parametrize("chunk", [1 << 20, 5])  # one chunk of pixels, or a few pixels each
def test_roi_confusion_matches_pixel_loop(seed: int, roi_kind: str, chunk: int, monkeypatch):
    monkeypatch.setattr(functional_roi, "CONFUSION_CHUNK", chunk)
    g = torch.Generator().manual_seed(seed)
    b, k, h, w, n, r = 2, 3, 5, 7, 4, 2
    preds = torch.randint(0, n, (b, k, h, w), generator=g)
    target = torch.randint(0, n, (b, h, w), generator=g)
    target[torch.rand(b, h, w, generator=g) < 0.2] = IGNORE
    roi = torch.randint(0, r + 1, (b, h, w), generator=g)
    arg = {"none": None, "shared": roi[0], "per_image": roi}[roi_kind]
    full_roi = {"none": torch.zeros_like(roi), "shared": roi[0].expand_as(roi), "per_image": roi}
    expected = confusion_reference(preds, target, full_roi[roi_kind], n, r)
    cm = roi_confusion(preds, target, arg, num_classes=n, num_rois=r)
    assert cm.dtype == torch.int64
    np.testing.assert_array_equal(cm.numpy(), expected)
    # 3-D preds: one rule, no K axis.
    one = roi_confusion(preds[:, 1], target, arg, num_classes=n, num_rois=r)
    np.testing.assert_array_equal(one.numpy(), expected[1])


def test_roi_confusion_hand_case() -> None:
    preds = torch.tensor([[[2, 2], [0, 1]]])
    target = torch.tensor([[[2, 0], [255, 1]]])
    roi = torch.tensor([[1, 2], [1, 0]])
    cm = roi_confusion(preds, target, roi, num_classes=3, num_rois=2)
    expected = torch.zeros(3, 3, 3, dtype=torch.long)
    expected[0, 2, 2] = expected[0, 0, 2] = expected[0, 1, 1] = 1  # whole image, ignored pixel out
    expected[1, 2, 2] = 1  # RoI 1: pixel (0, 0); its other pixel (1, 0) is ignored
    expected[2, 0, 2] = 1  # RoI 2: pixel (0, 1)
    assert torch.equal(cm, expected)


def test_precision_recall_iou_hand_case_and_nan() -> None:
    # rows = target, columns = prediction; class 2 absent everywhere, class 3 only predicted.
    cm = torch.tensor([[3, 1, 0, 0], [2, 4, 0, 1], [0, 0, 0, 0], [0, 0, 0, 0]])
    precision, recall = precision_recall(cm)
    iou = iou_from_confusion(cm)
    assert precision.dtype == recall.dtype == iou.dtype == torch.float64
    np.testing.assert_allclose(precision[[0, 1, 3]], [3 / 5, 4 / 5, 0.0])
    np.testing.assert_allclose(recall[[0, 1]], [3 / 4, 4 / 7])
    np.testing.assert_allclose(iou[[0, 1, 3]], [3 / 6, 4 / 8, 0.0])
    assert precision[2].isnan() and recall[2].isnan() and recall[3].isnan() and iou[2].isnan()


def test_mean_iou_against_a_pixel_loop_with_deferred_pixels() -> None:
    """mIoU of counts (deferred pixels: misses of their class) = the mean, over the classes
    present in the labels or the decisions, of |decided c and labelled c| / |either|."""
    g = torch.Generator().manual_seed(3)
    target = torch.randint(0, 4, (200,), generator=g)
    preds = torch.randint(0, 5, (200,), generator=g)  # 4: deferred
    preds[target == 2] = 0  # class 2 labelled, never decided
    target[target == 3] = 1  # class 3 decided, never labelled
    cm = torch.zeros(4, 4, dtype=torch.long)
    deferred = torch.zeros(4, dtype=torch.long)
    for t, d in zip(target.tolist(), preds.tolist(), strict=True):
        if d == 4:
            deferred[t] += 1
        else:
            cm[t, d] += 1
    ious = []
    for c in range(4):
        both = ((preds == c) & (target == c)).sum().item()
        either = ((preds == c) | (target == c)).sum().item()
        if either:
            ious.append(both / either)
    assert mean_iou(cm, deferred).item() == pytest.approx(sum(ious) / len(ious), abs=1e-15)
    assert mean_iou(torch.zeros(2, 2, 2, dtype=torch.long)).isnan().all()  # nothing counted
    assert (
        roi_metrics(cm[None, None], deferred[None, None])["miou"].item()
        == mean_iou(cm, deferred).item()
    )


def test_undefined_ratios_are_nan_not_zero_or_one() -> None:
    target = torch.full((1, 3, 4), IGNORE)
    target[0, 0, 0] = 1
    preds = torch.ones(1, 3, 4, dtype=torch.long)
    roi = torch.ones(3, 4, dtype=torch.long)  # RoI 2 is empty
    precision, recall = precision_recall(roi_confusion(preds, target, roi, 3, 2))
    assert precision[2].isnan().all() and recall[2].isnan().all()  # empty RoI
    assert precision[0, 0].isnan() and recall[0, 2].isnan()  # class absent
    assert precision[0, 1] == recall[0, 1] == 1.0
    all_ignored = roi_confusion(preds, torch.full_like(target, IGNORE), roi, 3, 2)
    assert iou_from_confusion(all_ignored).isnan().all()
    assert all(v.isnan().all() for v in precision_recall(all_ignored))


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"preds": torch.zeros(2, 3)}, "preds"),
        ({"preds": torch.zeros(1, 2, 3)}, "preds"),  # float
        ({"target": torch.zeros(1, 2, 4, dtype=torch.long)}, "target"),
        ({"roi": torch.zeros(3, 3, dtype=torch.long)}, "roi"),
        ({"roi": torch.full((2, 3), 5)}, r"roi ids in 0\.\.4"),
        ({"preds": torch.full((1, 2, 3), 19)}, r"preds in \[0, 19\)"),
        ({"target": torch.full((1, 2, 3), 20)}, "target in"),
    ],
)
def test_roi_confusion_rejects_bad_input(kwargs: dict, match: str) -> None:
    args = {"preds": torch.zeros(1, 2, 3, dtype=torch.long), "target": torch.zeros(1, 2, 3).long()}
    with pytest.raises(ValueError, match=match):
        roi_confusion(**(args | kwargs))


def components(mask: np.ndarray) -> list[list[tuple[int, int]]]:
    """8-connected components by breadth-first flood fill, independent of scipy."""
    h, w = mask.shape
    seen = np.zeros_like(mask, dtype=bool)
    out = []
    for y0 in range(h):
        for x0 in range(w):
            if not mask[y0, x0] or seen[y0, x0]:
                continue
            seen[y0, x0] = True
            queue, comp = deque([(y0, x0)]), []
            while queue:
                y, x = queue.popleft()
                comp.append((y, x))
                for dy in (-1, 0, 1):
                    for dx in (-1, 0, 1):
                        v, u = y + dy, x + dx
                        if 0 <= v < h and 0 <= u < w and mask[v, u] and not seen[v, u]:
                            seen[v, u] = True
                            queue.append((v, u))
            out.append(comp)
    return out


def segment_reference(pred, target, cls, roi, num_rois):
    """segment_errors' result from flood-filled components and per-segment pixel votes."""
    pred_mask, gt_mask = (pred == cls) & (target != IGNORE), target == cls
    pred_segs, gt_segs = components(pred_mask), components(gt_mask)
    fp = [s for s in pred_segs if not any(gt_mask[p] for p in s)]
    fn = [s for s in gt_segs if not any(pred[p] == cls for p in s)]

    def owner(seg):
        votes = Counter(int(roi[p]) for p in seg)
        return min(r for r, c in votes.items() if c == max(votes.values()))

    def per_roi(segs):
        counts = [len(segs)] + [0] * num_rois
        for s in segs:
            counts[owner(s)] += owner(s) > 0
        return counts

    def mask_of(segs):
        m = np.zeros(pred.shape, dtype=bool)
        for s in segs:
            m[tuple(np.array(s).T)] = True
        return m

    return {
        "fp": len(fp),
        "fn": len(fn),
        "n_pred": len(pred_segs),
        "n_gt": len(gt_segs),
        "fp_mask": mask_of(fp),
        "fn_mask": mask_of(fn),
        "fp_roi": per_roi(fp),
        "fn_roi": per_roi(fn),
        "n_pred_roi": per_roi(pred_segs),
        "n_gt_roi": per_roi(gt_segs),
    }


def check_against_reference(pred: np.ndarray, target: np.ndarray, roi: np.ndarray, cls: int):
    out = segment_errors(torch.from_numpy(pred), torch.from_numpy(target), cls, IGNORE,
                         torch.from_numpy(roi), num_rois=3)  # fmt: skip
    ref = segment_reference(pred, target, cls, roi, num_rois=3)
    for key, value in ref.items():
        got = out[key]
        np.testing.assert_array_equal(got.numpy() if torch.is_tensor(got) else got, value, key)
    eight = np.ones((3, 3), dtype=bool)
    assert ref["n_gt"] == ndimage.label(target == cls, structure=eight)[1]
    assert ref["n_pred"] == ndimage.label((pred == cls) & (target != IGNORE), structure=eight)[1]


@settings(max_examples=60, deadline=None)
@given(data=st.data())
def test_segment_errors_match_flood_fill(data: st.DataObject) -> None:
    shape = data.draw(st.tuples(st.integers(1, 12), st.integers(1, 16)))
    pred = data.draw(hnp.arrays(np.int64, shape, elements=st.sampled_from([3, 3, 5, 7])))
    target = data.draw(hnp.arrays(np.int64, shape, elements=st.sampled_from([3, 3, 5, IGNORE])))
    roi = data.draw(hnp.arrays(np.int64, shape, elements=st.integers(0, 3)))
    check_against_reference(pred, target, roi, cls=3)


@pytest.mark.parametrize("seed", range(10))
def test_segment_errors_match_flood_fill_on_blobs(seed: int) -> None:
    # Smooth random fields give larger, irregular segments than independent pixels.
    rng = np.random.default_rng(seed)
    fields = ndimage.zoom(rng.random((4, 4, 6)), (1, 3, 8 / 3), order=1)
    pred = np.where(fields[0] > 0.5, 3, 5)
    target = np.where(fields[1] > 0.55, 3, np.where(fields[2] > 0.8, IGNORE, 5))
    roi = (fields[3] * 4).astype(np.int64)
    check_against_reference(pred, target, roi, cls=3)


def test_segment_errors_hand_case() -> None:
    pred = torch.tensor(
        [
            [1, 0, 0, 0, 0, 1],
            [0, 1, 0, 0, 0, 0],  # (0, 0) and (1, 1) touch diagonally: ONE segment
            [0, 0, 0, 0, 1, 1],
            [0, 0, 0, 0, 0, 0],
        ]
    )
    target = torch.tensor(
        [
            [0, 0, 0, 0, 0, 0],
            [0, 1, 0, 0, 0, 0],  # hits the diagonal pair: a true positive
            [0, 0, 0, 0, 0, 0],
            [1, 1, 0, 255, 0, 0],  # a missed ground-truth segment: FN
        ]
    )
    roi = torch.tensor(
        [
            [1, 1, 1, 1, 1, 2],  # FP (0, 5) is alone in RoI 2
            [1, 2, 1, 1, 1, 1],
            [1, 1, 1, 1, 1, 2],  # FP (2, 4)-(2, 5): one pixel each in RoI 1 and 2: tie → 1
            [3, 0, 1, 1, 1, 1],  # FN segment: one pixel in RoI 3, one in none: tie → 0
        ]
    )
    out = segment_errors(pred, target, cls=1, roi=roi, num_rois=3)
    assert (out["fp"], out["fn"], out["n_pred"], out["n_gt"]) == (2, 1, 3, 2)
    # (0, 5) and (2, 4)-(2, 5) are two FP segments: two rows apart, not 8-connected.
    assert out["fp_mask"].nonzero().tolist() == [[0, 5], [2, 4], [2, 5]]
    assert out["fn_mask"].nonzero().tolist() == [[3, 0], [3, 1]]
    assert out["fp_roi"].tolist() == [2, 1, 1, 0]
    assert out["n_pred_roi"].tolist() == [3, 2, 1, 0]  # diagonal pair: one pixel each in 1, 2
    assert out["fn_roi"].tolist() == [1, 0, 0, 0]  # owned by "no RoI": whole image only
    assert out["n_gt_roi"].tolist() == [2, 0, 1, 0]  # (1, 1) lies in RoI 2


def test_segment_errors_ignore_and_majority() -> None:
    pred = torch.tensor([[2, 2, 2, 2, 2]])
    target = torch.tensor([[0, 0, 255, 0, 0]])  # the ignored pixel splits the prediction in two
    roi = torch.tensor([[3, 1, 1, 3, 3]])  # left segment: tie between 3 and 1; right: all 3
    out = segment_errors(pred, target, cls=2, roi=roi, num_rois=3)
    assert (out["fp"], out["n_pred"], out["n_gt"]) == (2, 2, 0)
    assert out["fp_roi"].tolist() == [2, 1, 0, 1]
    assert "fp_roi" not in segment_errors(pred, target, cls=2)


def test_segment_errors_rejects_bad_input() -> None:
    pred = torch.zeros(3, 4, dtype=torch.long)
    with pytest.raises(ValueError, match="one shape"):
        segment_errors(pred, torch.zeros(3, 5, dtype=torch.long))
    with pytest.raises(ValueError, match="roi"):
        segment_errors(pred, pred, roi=torch.full((3, 4), 9), num_rois=4)
    with pytest.raises(ValueError, match="roi"):
        segment_errors(pred, pred, roi=pred[None])
    with pytest.raises(ValueError, match="cls"):
        segment_errors(pred, pred, cls=255)
