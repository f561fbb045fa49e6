"""The one segment counter, rule_errors: its compiled pass over a packed mask's runs (no location
maps) equals the definition (mask_segment_errors, itself tested against brute force in
test_metrics_functional.py), on widths that are and are not multiples of 64."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy import ndimage

from costseg.metrics import SegmentErrors
from costseg.metrics.functional import label_segments, mask_segment_errors, rule_errors
from costseg.metrics.functional.segment_rules import pack_bits
from costseg.metrics.segment_runs import Prepared, run_counts


def blobs(rng: np.random.Generator, shape: tuple[int, int], smooth: float) -> np.ndarray:
    return ndimage.gaussian_filter(rng.standard_normal(shape), smooth)


def random_case(seed: int, width: int):
    """A smooth (H, width) ground truth and prediction, sometimes cut at word edges, sometimes
    empty or full, with or without a RoI map."""
    rng = np.random.default_rng(seed)
    shape = (int(rng.integers(1, 40)), width)
    base = blobs(rng, shape, rng.uniform(0.3, 3))
    gt = base > rng.uniform(-0.1, 0.1)
    pred = base + blobs(rng, shape, rng.uniform(0.3, 3)) > rng.uniform(-0.1, 0.1)
    pred[:, :: int(rng.integers(2, 70))] = seed % 2  # runs cut (or joined) at word edges
    if seed % 5 == 0:
        pred[:] = seed % 10 == 0  # full and empty masks
    num_rois = 4 if seed % 3 else 0
    roi = rng.integers(0, num_rois + 1, shape) if num_rois else None
    return pred, gt, roi, num_rois


WIDTHS = [1, 5, 63, 64, 65, 100, 128, 191, 192]


@pytest.mark.parametrize("width", WIDTHS)
@pytest.mark.parametrize("seed", range(6))
def test_run_counts_equal_the_definition(seed: int, width: int) -> None:
    pred, gt, roi, num_rois = random_case(seed * 31 + width, width)
    gt_segments = label_segments(gt, roi, num_rois)
    prepared = Prepared(gt, roi, num_rois, gt_segments)
    got = run_counts(np.packbits(pred.reshape(-1)), pred.shape, prepared)
    expected = mask_segment_errors(pred, gt, roi, num_rois, gt_segments).counts
    np.testing.assert_array_equal(got, expected)


@pytest.mark.parametrize("width", [13, 64, 70, 128])
def test_rule_errors_count_alike_with_and_without_maps(width: int) -> None:
    """K masks (some identical) of one image: the run pass (no maps) and the definition (maps)
    give the same counts for every rule; the maps are the definition's."""
    rng = np.random.default_rng(width)
    pred, gt, roi, num_rois = random_case(width + 1, width)
    masks = [pred, pred, ~pred, blobs(rng, pred.shape, 1.5) > 0, np.zeros_like(pred)]
    packed = np.packbits(np.stack(masks).reshape(len(masks), -1), axis=-1)
    fast, slow = (rule_errors(packed, gt, roi, num_rois, maps) for maps in (False, True))
    assert fast.fp is None and slow.fp is not None
    assert fast.inverse.tolist() == slow.inverse.tolist()
    for j, k in np.ndindex(len(masks), len(masks)):  # one entry per distinct mask
        assert (slow.inverse[j] == slow.inverse[k]) == np.array_equal(masks[j], masks[k])
    np.testing.assert_array_equal(fast.counts, slow.counts)
    for k, mask in enumerate(masks):
        u = slow.inverse[k]
        errors = mask_segment_errors(mask, gt, roi, num_rois)
        np.testing.assert_array_equal(slow.counts[u], errors.counts)
        assert np.array_equal(slow.fp[u], errors.fp_mask)
        assert np.array_equal(slow.fn[u], errors.fn_mask)


@pytest.mark.parametrize("fill", [(False, False), (True, False), (False, True), (True, True)])
@pytest.mark.parametrize("width", [5, 64])
def test_empty_and_full_masks(fill: tuple[bool, bool], width: int) -> None:
    pred, gt = (np.full((4, width), value) for value in fill)
    roi = np.arange(4 * width).reshape(4, width) % 3
    gt_segments = label_segments(gt, roi, 2)
    expected = mask_segment_errors(pred, gt, roi, 2, gt_segments).counts
    got = run_counts(np.packbits(pred.reshape(-1)), pred.shape, Prepared(gt, roi, 2, gt_segments))
    np.testing.assert_array_equal(got, expected)


def test_one_row_without_rois() -> None:
    """A (1, W) mask without RoIs: every component belongs to RoI 0."""
    pred = np.array([[True, False, True, True, False, True]])
    gt = np.array([[True, False, False, False, False, True]])
    gt_segments = label_segments(gt, None, 2)
    expected = mask_segment_errors(pred, gt, None, 2, gt_segments).counts
    got = run_counts(np.packbits(pred.reshape(-1)), pred.shape, Prepared(gt, None, 2, gt_segments))
    np.testing.assert_array_equal(got, expected)
    assert expected[:, 0].tolist() == [1, 0, 3, 2]  # hand-counted: fp, fn, n_pred, n_gt


@pytest.mark.parametrize("width", [56, 128])
def test_sweep_counts_equal_those_with_maps(width: int) -> None:
    gen = torch.Generator().manual_seed(width)
    smooth = torch.nn.functional.avg_pool2d(torch.rand(2, 6, 20, width, generator=gen), 5, 1, 2)
    rules = (smooth * 3).long().clamp(max=2)
    target = (torch.rand(2, 20, width, generator=gen) * 3).long()
    target[:, :3] = 255
    roi = torch.randint(0, 3, (20, width), generator=gen)
    outputs = []
    for size in ((0, 0), None):  # runs (no maps), then the definition with maps
        metric = SegmentErrors(classes=(1, 2), num_rules=6, num_rois=2, heatmap_size=size)
        metric.update(rules, target, roi)
        outputs.append(metric.compute())
    for name in ("fp", "fn", "n_pred", "n_gt"):
        assert torch.equal(outputs[0][name], outputs[1][name])
    assert outputs[1]["fp"].sum() > 0  # the case counts something


@pytest.mark.parametrize("shape", [(1, 1, 8), (2, 3, 13), (1, 4, 5 * 7)])
def test_masks_packed_in_torch_equal_numpy_packbits(shape: tuple[int, int, int]) -> None:
    # The GPU's packing (8 times fewer bytes to copy) against numpy's, odd pixel counts included.
    masks = torch.rand(shape, generator=torch.Generator().manual_seed(sum(shape))) > 0.5
    assert np.array_equal(pack_bits(masks).numpy(), np.packbits(masks.numpy(), axis=-1))
