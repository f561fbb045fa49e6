"""The compiled segment counts equal mask_segment_errors' numpy ones, and SegmentErrors without
location maps (which uses them) counts as with maps."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy import ndimage

from costseg.metrics import SegmentErrors
from costseg.metrics.functional import label_segments, mask_segment_errors
from costseg.metrics.segment_counts import mask_counts


def blobs(rng: np.random.Generator, shape: tuple[int, int], smooth: float, base=None):
    field = ndimage.gaussian_filter(rng.standard_normal(shape), smooth)
    return field if base is None else field + base


@pytest.mark.parametrize("seed", range(12))
@pytest.mark.parametrize("num_rois", [0, 4])
def test_counts_equal_the_numpy_ones(seed: int, num_rois: int) -> None:
    rng = np.random.default_rng(seed)
    shape = tuple(int(v) for v in rng.integers(3, 90, 2))
    base = blobs(rng, shape, rng.uniform(0.5, 3))
    gt = base > rng.uniform(-0.1, 0.1)
    pred = blobs(rng, shape, rng.uniform(0.5, 3), base) > rng.uniform(-0.1, 0.1)
    roi = rng.integers(0, num_rois + 1, shape) if num_rois else None
    gt_segments = label_segments(gt, roi, num_rois)
    expected = mask_segment_errors(pred, gt, roi, num_rois, gt_segments).counts
    np.testing.assert_array_equal(mask_counts(pred, gt, roi, num_rois, gt_segments), expected)


@pytest.mark.parametrize("fill", [(False, False), (True, False), (False, True), (True, True)])
def test_empty_and_full_masks(fill: tuple[bool, bool]) -> None:
    pred, gt = (np.full((4, 5), value) for value in fill)
    roi = np.arange(20).reshape(4, 5) % 3
    gt_segments = label_segments(gt, roi, 2)
    expected = mask_segment_errors(pred, gt, roi, 2, gt_segments).counts
    np.testing.assert_array_equal(mask_counts(pred, gt, roi, 2, gt_segments), expected)


def test_segment_errors_without_maps_counts_as_with_them() -> None:
    rng = np.random.default_rng(7)
    base = blobs(rng, (2, 40, 56), 2)
    target = torch.from_numpy(np.where(base > 0, 3, 1))
    preds = torch.stack(
        [torch.from_numpy(np.where(blobs(rng, (2, 40, 56), 2) > t, 3, 0)) for t in (0, 0.1)],
        1,
    )
    roi = torch.from_numpy(rng.integers(0, 5, (40, 56)))
    with_maps = SegmentErrors(classes=(3,), num_rules=2, heatmap_size=(40, 56))
    without = SegmentErrors(classes=(3,), num_rules=2, heatmap_size=(0, 0))
    for metric in (with_maps, without):
        metric.update(preds, target, roi)
    for key in ("fp", "fn", "n_pred", "n_gt"):
        assert torch.equal(without.compute()[key], with_maps.compute()[key])
    assert with_maps.compute()["fp"].sum() > 0  # the case counts something


@pytest.mark.parametrize("shape", [(1, 1, 8), (2, 3, 13), (1, 4, 5 * 7)])
def test_masks_packed_in_torch_equal_numpy_packbits(shape: tuple[int, int, int]) -> None:
    # The GPU's packing (8 times fewer bytes to copy) against numpy's, odd pixel counts included.
    from costseg.metrics.functional.segment_rules import pack_bits

    masks = torch.rand(shape, generator=torch.Generator().manual_seed(sum(shape))) > 0.5
    assert np.array_equal(pack_bits(masks).numpy(), np.packbits(masks.numpy(), axis=-1))


def test_one_row_without_rois() -> None:
    """A (1, W) mask without RoIs: every component belongs to RoI 0 (the compiled pass once
    took the (1, 1) stand-in for a RoI map of that height and read past it)."""
    pred = np.array([[True, False, True, True, False, True]])
    gt = np.array([[True, False, False, False, False, True]])
    gt_segments = label_segments(gt, None, 2)
    expected = mask_segment_errors(pred, gt, None, 2, gt_segments).counts
    np.testing.assert_array_equal(mask_counts(pred, gt, None, 2, gt_segments), expected)
