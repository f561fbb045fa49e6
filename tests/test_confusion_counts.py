"""The compiled confusion counts equal roi_confusion's tensor operations, and RoIPrecisionRecall
counts a sweep (which takes them) as it counts the same rules one by one."""

from __future__ import annotations

import pytest
import torch

from costseg.metrics import RoIPrecisionRecall
from costseg.metrics.confusion_counts import count_confusion
from costseg.metrics.functional import roi_confusion
from costseg.metrics.functional.roi import COMPILED_MIN_RULES


def sweep_like(gen: torch.Generator, b: int, k: int, h: int, w: int, n: int) -> torch.Tensor:
    """(B, K, H, W) labels that mostly agree across rules, as a sweep's do."""
    rules = torch.randint(0, n, (b, 1, h, w), generator=gen).expand(b, k, h, w).clone()
    flip = torch.rand(b, k, h, w, generator=gen) < 0.2
    rules[flip] = torch.randint(0, n, (int(flip.sum()),), generator=gen)
    return rules


@pytest.mark.parametrize("seed", range(6))
@pytest.mark.parametrize("dtype", [torch.uint8, torch.int64])
@pytest.mark.parametrize("roi_kind", ["none", "shared", "per image"])
def test_counts_equal_roi_confusion(seed: int, dtype: torch.dtype, roi_kind: str) -> None:
    gen = torch.Generator().manual_seed(seed)
    b, k, h, w, n, r = 2, 1 + 7 * seed, 9 + seed, 13, 5, 3
    rules = sweep_like(gen, b, k, h, w, n).to(dtype)
    target = torch.randint(0, n, (b, h, w), generator=gen)
    target[torch.rand(b, h, w, generator=gen) < 0.2] = 255
    shape = {"none": None, "shared": (h, w), "per image": (b, h, w)}[roi_kind]
    roi = None if shape is None else torch.randint(0, r + 1, shape, generator=gen)
    expected = roi_confusion(rules, target, roi, n, r, 255)
    assert torch.equal(count_confusion(rules, target, roi, n, r, 255), expected)


def test_hand_counted_case() -> None:
    rules = torch.tensor([[[[0, 1], [1, 1]], [[0, 0], [1, 0]]]])  # (1, 2, 2, 2)
    target = torch.tensor([[[0, 1], [0, 255]]])
    roi = torch.tensor([[1, 0], [1, 1]])
    cm = count_confusion(rules, target, roi, 2, 1, 255)
    # (target, label) of the three counted pixels (RoI 1, outside, RoI 1):
    # rule 0: (0, 0), (1, 1), (0, 1); rule 1: (0, 0), (1, 0), (0, 1)
    assert cm.tolist() == [
        [[[1, 1], [0, 1]], [[1, 1], [0, 0]]],
        [[[1, 1], [1, 0]], [[1, 1], [0, 0]]],
    ]


def test_empty_images_and_bad_inputs() -> None:
    empty = count_confusion(torch.zeros(1, 3, 0, 4, dtype=torch.long),
                            torch.zeros(1, 0, 4, dtype=torch.long), None, 4, 2, 255)  # fmt: skip
    assert empty.shape == (3, 3, 4, 4) and int(empty.sum()) == 0
    target = torch.zeros(1, 2, 2, dtype=torch.long)
    with pytest.raises(ValueError, match="expected preds in"):
        count_confusion(torch.full((1, 3, 2, 2), 7), target, None, 4, 0, 255)
    with pytest.raises(ValueError, match="expected target in"):
        count_confusion(torch.zeros(1, 3, 2, 2, dtype=torch.long), target + 9, None, 4, 0, 255)
    with pytest.raises(ValueError, match="expected roi ids"):
        count_confusion(torch.zeros(1, 3, 2, 2, dtype=torch.long), target, target + 5, 4, 2, 255)


def test_metric_counts_a_sweep_as_single_rules() -> None:
    gen = torch.Generator().manual_seed(0)
    k, n = COMPILED_MIN_RULES + 3, 6
    rules = sweep_like(gen, 2, k, 11, 12, n)
    target = torch.randint(0, n, (2, 11, 12), generator=gen)
    roi = torch.randint(0, 3, (11, 12), generator=gen)
    sweep = RoIPrecisionRecall(num_classes=n, num_rules=k, num_rois=2)
    sweep.update(rules.to(torch.uint8), target, roi)
    for rule in range(k):
        single = RoIPrecisionRecall(num_classes=n, num_rules=1, num_rois=2)
        single.update(rules[:, rule], target, roi)
        assert torch.equal(sweep.confmat[rule], single.confmat[0])
