"""The fused decide-and-count pass (costseg.decision.counts) against decide_reference and a
bincount written here as a loop, and against roi_confusion of decide's labels."""

import pytest
import torch
from decision_inputs import VERTICES, defer_ties, smooth

from costseg.costs import with_defer
from costseg.decision import (
    count_decisions,
    decide,
    decide_counts,
    decide_reference,
    prepare_counts,
    subsample,
)
from costseg.metrics.functional.roi import roi_confusion

DEFERRING = with_defer(VERTICES[1], torch.linspace(0.5, 20, 19, dtype=torch.float64))
MATRICES = {
    "altruistic": VERTICES[1],
    "egoistic": VERTICES[2],
    "dense": torch.rand(19, 19, generator=torch.Generator().manual_seed(5), dtype=torch.float64),
    "defer": DEFERRING,
    "egoistic defer": with_defer(VERTICES[2], 1.0),
}


def counted_by_loop(probs, cost, labels, roi, priors, num_rois):
    """decide_reference (a regional stack: with the RoI map), then every labelled pixel counted
    one by one."""
    b, n, h, w = probs.shape
    confusion = torch.zeros(b, num_rois + 1, n, n + 1, dtype=torch.long)
    agree = torch.zeros(b, dtype=torch.long)
    for i in range(b):
        own = priors[i] if priors is not None and priors.ndim == 4 else priors
        regions = roi if cost is not None and cost.ndim == 3 else None
        decided = decide_reference(probs[i : i + 1], cost, own, regions)[0]
        best = probs[i].argmax(0)
        region = torch.zeros(h, w, dtype=torch.long) if roi is None else roi.expand(b, h, w)[i]
        for y in range(h):
            for x in range(w):
                t, d = labels[i, y, x].item(), decided[y, x].item()
                if t == 255:
                    continue
                column = n if d == 255 else d
                confusion[i, 0, t, column] += 1
                if region[y, x] > 0:
                    confusion[i, region[y, x], t, column] += 1
                agree[i] += d == best[y, x].item()
    return confusion, agree


def tied(shape, seed):
    """Probabilities with exact ties: values from a few levels, normalised by a power of two."""
    gen = torch.Generator().manual_seed(seed)
    levels = torch.randint(0, 4, shape, generator=gen).float()
    return levels / 64


def batch(shape, seed, share_ignored=0.2):
    b, n, h, w = shape
    gen = torch.Generator().manual_seed(seed)
    labels = torch.randint(0, n, (b, h, w), generator=gen)
    labels[torch.rand(b, h, w, generator=gen) < share_ignored] = 255
    roi = torch.randint(0, 5, (h, w), generator=gen)
    return labels, roi


@pytest.mark.parametrize("path", ["numba", "torch"])
@pytest.mark.parametrize("name", list(MATRICES))
@pytest.mark.parametrize("priors_kind", [None, "global", "pixel", "per image"])
def test_counts_equal_the_reference_and_a_loop(path, name, priors_kind):
    shape = (2, 19, 7, 13)
    probs = torch.cat([smooth((1, 19, 7, 13), 3), tied((1, 19, 7, 13), 4)])
    labels, roi = batch(shape, 1)
    gen = torch.Generator().manual_seed(2)
    priors = {
        None: None,
        "global": torch.rand(19, generator=gen) + 0.05,
        "pixel": torch.rand(19, 7, 13, generator=gen) + 0.05,
        "per image": torch.rand(*shape, generator=gen) + 0.05,
    }[priors_kind]
    cost = MATRICES[name]
    for region in (None, roi, roi.expand(2, -1, -1).clone()):
        got = count_decisions(prepare_counts(probs, labels, region, priors), cost, path=path)
        confusion, agree = counted_by_loop(probs, cost, labels, region, priors, 4)
        assert torch.equal(got.confusion, confusion) and torch.equal(got.agree, agree)


@pytest.mark.parametrize("shape", [(1, 19, 1, 1), (3, 19, 5, 3), (1, 19, 33, 65), (4, 5, 9, 11)])
def test_batch_sizes_and_odd_image_sizes_against_roi_confusion(shape):
    b, n = shape[:2]
    probs = smooth(shape, 7, scale=2)
    labels, roi = batch(shape, 8)
    roi = roi % 3
    costs = [VERTICES[2]] if n == 19 else []
    costs += [torch.rand(n, n, generator=torch.Generator().manual_seed(n)).double()]
    costs += [with_defer(costs[-1], 0.3)]
    for cost in costs:
        got = decide_counts(probs, cost, labels, roi, num_rois=2)
        decided = decide(probs, cost)
        assert torch.equal(
            got.confusion.sum(0), roi_confusion(decided, labels, roi, n, 2, deferred=255)
        )
        for i in range(b):
            one = roi_confusion(decided[i : i + 1], labels[i : i + 1], roi, n, 2, deferred=255)
            assert torch.equal(got.confusion[i], one)
        assert torch.equal(got.agree, ((decided == probs.argmax(1)) & (labels != 255)).sum((1, 2)))


def test_near_ties_with_deferring_are_decided_again_exactly():
    probs = defer_ties(DEFERRING, 28, seed=8)  # (1, 19, 1, P): a class and deferring a hair apart
    labels = torch.randint(0, 19, probs.shape[:1] + probs.shape[2:])
    got = decide_counts(probs, DEFERRING, labels, num_rois=0)
    want, agree = counted_by_loop(probs, DEFERRING, labels, None, None, 0)
    assert torch.equal(got.confusion, want) and torch.equal(got.agree, agree)
    assert 0 < got.confusion[..., 19].sum() < labels.numel()


def test_every_label_ignored_and_prepared_inputs_for_many_matrices():
    probs = smooth((2, 19, 4, 4), 1)
    labels = torch.full((2, 4, 4), 255)
    assert decide_counts(probs, VERTICES[1], labels).confusion.sum() == 0
    labels, roi = batch((2, 19, 4, 4), 2)
    prepared = prepare_counts(probs, labels, roi)
    for cost in (*VERTICES, DEFERRING):
        assert torch.equal(
            count_decisions(prepared, cost).confusion,
            decide_counts(probs, cost, labels, roi).confusion,
        )


def test_subsample_keeps_a_fixed_share_of_labelled_pixels():
    shape = (3, 19, 16, 20)
    probs = smooth(shape, 2)
    labels, roi = batch(shape, 3, share_ignored=0.5)
    priors = torch.rand(19, 16, 20) + 0.1
    part = subsample(probs, labels, roi, priors, share=0.25, seed=4)
    again = subsample(probs, labels, roi, priors, share=0.25, seed=4)
    assert all(torch.equal(x, y) for x, y in zip(part, again, strict=True))
    kept = (part.labels != 255).sum((1, 2))
    labelled = (labels != 255).sum((1, 2))
    assert torch.equal(kept, (labelled * 0.25).ceil().long())
    got = decide_counts(part.probs, VERTICES[2], part.labels, part.roi, part.priors)
    want, agree = counted_by_loop(part.probs, VERTICES[2], part.labels, part.roi, part.priors, 4)
    assert torch.equal(got.confusion, want) and torch.equal(got.agree, agree)
    whole = decide_counts(probs, VERTICES[2], labels, roi, priors)
    assert (got.confusion <= whole.confusion).all()  # a subset of the pixels
    assert subsample(probs, labels, share=1.0).labels.ne(255).sum() == labelled.sum()


def test_wrong_inputs_raise():
    probs = smooth((1, 3, 2, 2), 0)
    with pytest.raises(ValueError, match="labels must lie"):
        decide_counts(probs, None, torch.full((1, 2, 2), 3))
    with pytest.raises(ValueError, match="labels must be"):
        decide_counts(probs, None, torch.zeros(1, 2, 3, dtype=torch.long))
    with pytest.raises(ValueError, match="roi ids"):
        decide_counts(probs, None, torch.zeros(1, 2, 2, dtype=torch.long), torch.full((2, 2), 9))
    with pytest.raises(ValueError, match="share"):
        subsample(probs, torch.zeros(1, 2, 2, dtype=torch.long), share=0)


@pytest.mark.parametrize("path", ["numba", "torch"])
@pytest.mark.parametrize("priors_kind", [None, "pixel"])
def test_a_regional_stack_counts_each_rois_pixels_under_its_matrix(path, priors_kind):
    """A regional stack (docs/definitions.md §21): each pixel decided by its RoI's matrix, the
    counts those of decide_reference with the RoI map; a stack of equal matrices counts as the
    one matrix."""
    shape = (2, 19, 7, 13)
    probs = torch.cat([smooth((1, 19, 7, 13), 3), tied((1, 19, 7, 13), 4)])
    labels, roi = batch(shape, 6)
    priors = None if priors_kind is None else torch.rand(19, 7, 13) + 0.05
    stack = torch.stack([VERTICES[0], VERTICES[1], VERTICES[2], MATRICES["dense"], VERTICES[1]])
    inputs = prepare_counts(probs, labels, roi, priors)
    for cost in (stack, torch.stack([VERTICES[2]] * 5)):
        got = count_decisions(inputs, cost, path=path)
        confusion, agree = counted_by_loop(probs, cost, labels, roi, priors, 4)
        assert torch.equal(got.confusion, confusion) and torch.equal(got.agree, agree)
