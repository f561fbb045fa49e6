"""The compiled packing of every class's masks equals np.packbits of the boolean masks, and
SegmentErrors counts uint8 rules (which take it) as it counts the same rules as int64."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from costseg.metrics import SegmentErrors
from costseg.metrics.mask_bits import packed_class_masks


@pytest.mark.parametrize("seed", range(5))
def test_packing_equals_packbits(seed: int) -> None:
    gen = torch.Generator().manual_seed(seed)
    b, k, h, w = 2, 3 + seed, 4 + 2 * seed, 8
    rules = torch.randint(0, 6, (b, k, h, w), generator=gen, dtype=torch.uint8)
    valid = torch.rand(b, h, w, generator=gen) < 0.8
    classes = (0, 5, 2, 200)
    packed = packed_class_masks(rules, classes, valid)
    for c, cls in enumerate(classes):
        masks = ((rules == cls) & valid[:, None]).flatten(2).numpy()
        np.testing.assert_array_equal(packed[c], np.packbits(masks, axis=-1))


def test_other_rules_are_left_to_the_caller() -> None:
    valid = torch.ones(1, 3, 3, dtype=torch.bool)
    assert packed_class_masks(torch.zeros(1, 2, 3, 3, dtype=torch.uint8), (1,), valid) is None
    assert packed_class_masks(torch.zeros(1, 2, 2, 4, dtype=torch.long), (1,), valid) is None


def test_segment_errors_count_uint8_rules_as_int64_ones() -> None:
    gen = torch.Generator().manual_seed(0)
    rules = torch.randint(0, 3, (2, 5, 16, 12), generator=gen)
    target = torch.randint(0, 3, (2, 16, 12), generator=gen)
    target[:, :2] = 255
    roi = torch.randint(0, 3, (16, 12), generator=gen)
    counts = []
    for dtype in (torch.long, torch.uint8):
        metric = SegmentErrors(classes=(1, 2), num_rules=5, num_rois=2, heatmap_size=(0, 0))
        metric.update(rules.to(dtype), target, roi)
        counts.append(metric.compute())
    for name in ("fp", "fn", "n_pred", "n_gt"):
        assert torch.equal(counts[0][name], counts[1][name])
