"""The counts from a packed mask's runs equal the compiled pixel pass (mask_counts, itself
tested against mask_segment_errors), and SegmentErrors counts as with location maps when its
masks' rows are whole 64-bit words (which takes the runs)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy import ndimage

from costseg.metrics import SegmentErrors
from costseg.metrics.functional import label_segments
from costseg.metrics.segment_counts import mask_counts
from costseg.metrics.segment_runs import Prepared, run_counts


def blobs(rng: np.random.Generator, shape: tuple[int, int], smooth: float) -> np.ndarray:
    return ndimage.gaussian_filter(rng.standard_normal(shape), smooth)


@pytest.mark.parametrize("seed", range(40))
def test_run_counts_equal_the_pixel_pass(seed: int) -> None:
    rng = np.random.default_rng(seed)
    shape = (int(rng.integers(1, 50)), 64 * int(rng.integers(1, 4)))
    base = blobs(rng, shape, rng.uniform(0.3, 3))
    gt = base > rng.uniform(-0.1, 0.1)
    pred = base + blobs(rng, shape, rng.uniform(0.3, 3)) > rng.uniform(-0.1, 0.1)
    pred[:, :: int(rng.integers(2, 70))] = seed % 2  # runs cut (or joined) at word edges
    if seed % 5 == 0:
        pred[:] = seed % 10 == 0  # full and empty masks
    num_rois = 4 if seed % 3 else 0
    roi = rng.integers(0, num_rois + 1, shape) if num_rois else None
    gt_segments = label_segments(gt, roi, num_rois)
    prepared = Prepared(gt, roi, num_rois, gt_segments)
    got = run_counts(np.packbits(pred, axis=-1).reshape(-1), shape, prepared)
    np.testing.assert_array_equal(got, mask_counts(pred, gt, roi, num_rois, gt_segments))


def test_sweep_counts_equal_those_with_maps() -> None:
    gen = torch.Generator().manual_seed(0)
    smooth = torch.nn.functional.avg_pool2d(torch.rand(2, 6, 20, 128, generator=gen), 5, 1, 2)
    rules = (smooth * 3).long().clamp(max=2)
    target = (torch.rand(2, 20, 128, generator=gen) * 3).long()
    target[:, :3] = 255
    roi = torch.randint(0, 3, (20, 128), generator=gen)
    outputs = []
    for size in ((0, 0), None):  # runs (no maps), then the pixel path with maps
        metric = SegmentErrors(classes=(1, 2), num_rules=6, num_rois=2, heatmap_size=size)
        metric.update(rules, target, roi)
        outputs.append(metric.compute())
    for name in ("fp", "fn", "n_pred", "n_gt"):
        assert torch.equal(outputs[0][name], outputs[1][name])
