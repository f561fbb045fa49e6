"""Instance metrics (docs/definitions.md §9) against a brute-force loop over the instances of
generated scenes, with crowd regions, instances cut by ignored pixels and instances on RoI
borders; batches against one pass (two DDP processes: tests/test_metrics_ddp.py)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from instance_reference import SIZES, reference_instances

from costseg.classes import INSTANCE_CLASSES, LABEL_ID_TO_TRAIN_ID, class_index
from costseg.data.toy.dataset import StreetScenes
from costseg.metrics.instances import InstanceMisses, instance_misses
from costseg.metrics.per_image import per_image_counts, per_image_loss
from costseg.metrics.selection import metric_values, parse_target, risk_level

PERSON, CAR, BUILDING = class_index("person"), class_index("car"), class_index("building")
CLASSES = (PERSON, CAR)
SIZE = (64, 128)


def scenes(n: int = 4) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(n, H, W) labels and instance ids of toy scenes, edited to hold the hard cases."""
    items = [StreetScenes("val", n, SIZE, seed=4).with_instances(i) for i in range(n)]
    labels = torch.stack([t for _, t, _ in items])
    ids = torch.stack([i for _, _, i in items])
    labels[0, :6, :10], ids[0, :6, :10] = PERSON, 24  # a crowd region: person, no instance
    people = ids[1].unique()
    people = people[(people >= 24000) & (people < 25000)]
    assert len(people) >= 2, "scene 1 should hold at least two persons"
    cut = ids[1] == people[0]
    rows = cut.nonzero()[:, 0]
    labels[1][cut & (torch.arange(SIZE[0])[:, None] < rows.float().median())] = 255  # cut
    labels[1][ids[1] == people[1]] = 255  # an instance wholly ignored: not counted
    return labels, ids, people


def predictions(labels: torch.Tensor, k: int = 3) -> torch.Tensor:
    """(n, K, H, W): the labels with more and more pixels replaced at random (30 %, 90 %,
    99.5 %, ...: instances are hit, cut and missed)."""
    g = torch.Generator().manual_seed(0)
    out = labels.clamp(max=18)[:, None].repeat(1, k, 1, 1)
    for r in range(k):
        drop = torch.rand(labels.shape, generator=g) < (0.3, 0.9, 0.995, 0.999)[r]
        out[:, r][drop] = torch.randint(0, 19, (int(drop.sum()),), generator=g)
    return out


def roi_blocks() -> torch.Tensor:
    """(H, W) RoI ids 0..4 in 8 x 8 blocks: many instances straddle a border, some tie."""
    g = torch.Generator().manual_seed(1)
    coarse = torch.randint(0, 5, (SIZE[0] // 8, SIZE[1] // 8), generator=g)
    return coarse.repeat_interleave(8, 0).repeat_interleave(8, 1)


def as_table(gt: torch.Tensor, missed: torch.Tensor) -> tuple[dict, dict]:
    """Nonzero entries of summed (C, A, R+1) / (K, C, A, R+1) counts as reference-style dicts."""
    g = {(CLASSES[c], SIZES[a], r): v for (c, a, r), v in _nonzero(gt)}
    m = {(k, CLASSES[c], SIZES[a], r): v for (k, c, a, r), v in _nonzero(missed)}
    return g, m


def _nonzero(t: torch.Tensor):
    return [(tuple(i.tolist()), int(t[tuple(i)])) for i in t.nonzero()]


def test_toy_instance_ids_agree_with_labels() -> None:
    image, label, ids = StreetScenes("val", 2, SIZE).with_instances(1)
    same_image, same_label = StreetScenes("val", 2, SIZE)[1]
    assert torch.equal(image, same_image) and torch.equal(label, same_label)
    label_ids = torch.where(ids >= 1000, ids // 1000, ids)
    assert torch.equal(torch.from_numpy(LABEL_ID_TO_TRAIN_ID)[label_ids].long(), label)
    things = ids[ids >= 1000] // 1000
    train = set(LABEL_ID_TO_TRAIN_ID[things.unique().numpy()].tolist())
    assert train <= set(INSTANCE_CLASSES) and PERSON in train


@pytest.mark.parametrize("with_roi", [True, False])
def test_counts_and_masks_equal_the_brute_force_loop(with_roi: bool) -> None:
    labels, ids, people = scenes()
    preds, roi = predictions(labels), roi_blocks() if with_roi else None
    out = instance_misses(preds, labels, ids, CLASSES, roi, masks=True)
    for b in range(len(labels)):
        gt, missed, masks = reference_instances(
            preds[b].numpy(), labels[b].numpy(), ids[b].numpy(),
            None if roi is None else roi.numpy(), CLASSES,
        )  # fmt: skip
        assert as_table(out.gt[b], out.missed[b]) == (gt, missed)
        assert np.array_equal(out.missed_mask[b].numpy(), masks)
    total, missed = out.gt[:, 0, :, 0].sum(), out.missed[:, :, 0, :, 0].sum((0, 2))
    assert missed[0] < missed[1] < missed[2] < total  # persons hit, cut and missed
    # the wholly ignored person is not counted, the cut one is
    kept = {v for v in ids[1].unique().tolist() if ((ids[1] == v) & (labels[1] != 255)).any()}
    assert people[0].item() in kept and people[1].item() not in kept


def test_ties_go_to_the_lowest_roi_and_crowds_count_nowhere() -> None:
    ids = torch.tensor([[[24000, 24000, 24000, 24000, 24, 24]]])
    target = torch.full((1, 1, 6), PERSON)
    roi = torch.tensor([[2, 2, 1, 1, 3, 3]])
    out = instance_misses(torch.zeros(1, 1, 6, dtype=torch.long), target, ids, (PERSON,), roi)
    assert out.gt[0, 0].sum(0).tolist() == [1, 1, 0, 0, 0]  # whole image, RoI 1 (the tie)
    assert out.missed[0, 0, 0].sum(0).tolist() == [1, 1, 0, 0, 0]


def test_area_limits_scale_with_the_label_size() -> None:
    # 128 x 256 labels: small < 16 px, medium < 144 px
    ids = torch.zeros(1, 128, 256, dtype=torch.long)
    ids[0, 0, :15], ids[0, 1, :16], ids[0, 2:4, :72] = 24000, 24001, 24002
    out = instance_misses(torch.zeros_like(ids), torch.full_like(ids, PERSON), ids, (PERSON,))
    assert out.missed[0, 0, 0, :, 0].tolist() == [1, 1, 1]


def test_batches_and_forward_equal_one_pass() -> None:
    labels, ids, _ = scenes()
    preds, roi = predictions(labels), roi_blocks()
    one, many = (InstanceMisses(CLASSES, 3, heatmap_size=(16, 32)) for _ in range(2))
    one.update(preds, labels, ids, roi)
    for part in ([0], [1, 2], [3]):
        many(preds[part], labels[part], ids[part], roi)  # forward: update and batch value
    a, b = one.compute(), many.compute()
    assert a.keys() == b.keys()
    for key in a:
        torch.testing.assert_close(a[key], b[key], rtol=0, atol=0, equal_nan=True)
    recall = a["instance_recall"]
    assert torch.equal(recall.isnan(), a["gt_instances"] == 0)
    assert a["missed_map"].shape == (3, 2, 16, 32) and 0 < a["missed_map"].max() <= 1


def test_per_image_loss_is_the_fraction_of_instances_missed() -> None:
    labels, ids, _ = scenes()
    preds, roi = predictions(labels), roi_blocks()
    counts = per_image_counts(preds, labels, roi, PERSON, 1, "instance_recall", instances=ids)
    losses = per_image_loss(counts, "instance_recall")
    for b in range(len(labels)):
        gt, missed, _ = reference_instances(
            preds[b].numpy(), labels[b].numpy(), ids[b].numpy(), roi.numpy(), CLASSES
        )
        n = sum(v for (c, _, r), v in gt.items() if c == PERSON and r == 1)
        for k in range(3):
            m = sum(v for (j, c, _, r), v in missed.items() if (j, c, r) == (k, PERSON, 1))
            want = m / n if n else float("nan")
            torch.testing.assert_close(losses[b, k].item(), want, equal_nan=True)
    with pytest.raises(ValueError, match="instance ids"):
        per_image_counts(preds, labels, roi, PERSON, 1, "instance_recall")


def test_targets_name_instance_recall() -> None:
    target = parse_target("person:roi1:instance_recall>=0.95")
    assert (target.cls, target.roi, target.metric) == (PERSON, 1, "instance_recall")
    assert risk_level(target) == pytest.approx(0.05)
    metric = InstanceMisses((CAR, PERSON), 2)
    labels, ids, _ = scenes(2)
    metric.update(predictions(labels, 2), labels, ids)
    out = metric.compute()
    values = metric_values({}, {}, target, [], out)
    torch.testing.assert_close(values, out["instance_recall"][:, 1, 1], equal_nan=True)
    with pytest.raises(ValueError, match="not measured"):
        metric_values({}, {}, parse_target("rider:roi1:instance_recall>=0.9"), [], out)


def test_bad_arguments() -> None:
    with pytest.raises(ValueError, match="instance classes"):
        InstanceMisses((BUILDING,))
    with pytest.raises(ValueError, match="instances of shape"):
        zeros = torch.zeros(1, 2, 2, dtype=torch.long)
        instance_misses(zeros, zeros, torch.zeros(1, 3, 2, dtype=torch.long))
