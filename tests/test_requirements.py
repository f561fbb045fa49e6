"""The design's per-image losses and objective from the fused count pass equal those of the
reference decision's label maps (``decide_reference``, ``per_image_counts``) on every image."""

import math

import pytest
import torch

from costseg.costs import load_cost, with_defer
from costseg.decision import count_decisions, decide_reference, prepare_counts
from costseg.metrics.per_image import per_image_counts, per_image_loss
from costseg.metrics.requirements import Requirements

TARGETS = [
    "person:roi1:recall>=0.8",
    "rider:roi0:recall>=0.5",
    "building:roi3:precision>=0.8",
    "person:roi0:handled_recall>=0.9",
    "car:roi2:fn_rate<=0.3",
    "person:roi1:fp_rate<=0.3",
]


def _batch(seed: int):
    g = torch.Generator().manual_seed(seed)
    probs = (3 * torch.randn(3, 19, 24, 40, generator=g)).softmax(1)
    labels = torch.randint(0, 19, (3, 24, 40), generator=g)
    labels[:, :, :5] = 255
    labels[1][labels[1] == 12] = 11  # an image without riders: an undefined loss
    roi = torch.randint(0, 5, (24, 40), generator=g)
    return probs, labels, roi


@pytest.mark.parametrize("cost", ["altruistic", "egoistic", "defer"])
def test_losses_from_counts_equal_the_reference_label_maps(cost):
    matrix = with_defer(load_cost("altruistic"), 0.4) if cost == "defer" else load_cost(cost)
    probs, labels, roi = _batch(0)
    req = Requirements.parse(TARGETS)
    counts = count_decisions(prepare_counts(probs, labels, roi), matrix)
    preds = decide_reference(probs, matrix)
    got = req.losses(counts.confusion, preds, labels, roi)
    for i, t in enumerate(req.constraints):
        parts = per_image_counts(preds[:, None], labels, roi, t.cls, t.roi, t.metric)
        expected = per_image_loss(parts, t.metric)[:, 0]
        torch.testing.assert_close(got[:, i], expected, equal_nan=True, rtol=0, atol=1e-12)
    assert math.isnan(got[1, 1])  # no rider in image 1


def test_the_objectives_pooled_over_images_against_a_loop():
    matrix = load_cost("egoistic")
    probs, labels, roi = _batch(1)
    counts = count_decisions(prepare_counts(probs, labels, roi), matrix)
    confusion, agree = counts.confusion.sum(0), counts.agree.sum()
    preds, valid = decide_reference(probs, matrix), labels != 255
    argmax = probs.argmax(1)
    agreement = Requirements.parse(TARGETS[:1]).value(confusion, agree)
    assert agreement == pytest.approx(((preds == argmax) & valid).sum().item() / valid.sum().item())
    ious = []
    for c in range(19):
        p, t = (preds == c) & valid, (labels == c) & valid
        if (p | t).any():
            ious.append(((p & t).sum() / (p | t).sum()).item())
    miou = Requirements.parse(TARGETS[:1], "miou").value(confusion, agree)
    assert miou == pytest.approx(sum(ious) / len(ious))
    precision = Requirements.parse(TARGETS[:1], "person:roi1:precision").value(confusion, agree)
    inside = valid & (roi == 1)
    tp = ((preds == 11) & (labels == 11) & inside).sum().item()
    assert precision == pytest.approx(tp / ((preds == 11) & inside).sum().item())


@pytest.mark.parametrize(
    ("targets", "objective", "message"),
    [
        (["person:roi1:recall>=1"], None, "no risk level"),
        (TARGETS[:1], "person:roi1:fp_rate", "pixel rate"),
        (TARGETS[:1], "person:roi1:sharpness", "unknown metric"),
    ],
)
def test_requirements_refuse_what_cannot_be_designed(targets, objective, message):
    with pytest.raises(ValueError, match=message):
        Requirements.parse(targets, objective)
