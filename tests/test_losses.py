"""The training losses (docs/definitions.md §16) against float64 loops written from the
definitions, PyTorch's own cross-entropy, and gradcheck; the module's priors for them."""

from __future__ import annotations

import math

import pytest
import torch
import torch.nn.functional as F
import yaml

from costseg.classes import CLASS_NAMES
from costseg.costs import load_cost
from costseg.models.deeplabv3plus import DeepLabV3Plus
from costseg.training.losses import (
    CrossEntropy,
    ExpectedCostCrossEntropy,
    FocalLoss,
    LogitAdjustedCrossEntropy,
    WeightedCrossEntropy,
    batch_mean,
    cost_weights,
)
from costseg.training.module import SegmentationModule

CLASSES = ("road", "sidewalk", "person", "car")  # car never occurs in the labels below
N = len(CLASSES)


def batch(dtype=torch.float64) -> tuple[torch.Tensor, torch.Tensor]:
    """(2, 4, 3, 5) logits and labels with ignored pixels and class 3 absent."""
    g = torch.Generator().manual_seed(0)
    logits = (3 * torch.randn(2, N, 3, 5, generator=g)).to(dtype)
    labels = torch.randint(0, 3, (2, 3, 5), generator=g)
    labels[0, 0, :3] = 255
    labels[1, 2, 4] = 255
    return logits, labels


def pixels(labels):
    """(b, y, x, true class) of every valid pixel, in a plain loop."""
    b, h, w = labels.shape
    for i in range(b):
        for y in range(h):
            for x in range(w):
                if labels[i, y, x] != 255:
                    yield i, y, x, int(labels[i, y, x])


def log_softmax_at(z, i, y, x) -> list[float]:
    v = [float(z[i, k, y, x]) for k in range(N)]
    m = max(v)
    s = math.log(sum(math.exp(t - m) for t in v)) + m
    return [t - s for t in v]


def reference(logits, labels, per_pixel, weight=lambda c: 1.0) -> float:
    """Σ weight(y) · per_pixel(log p, y, (i, y, x)) / Σ weight(y) over valid pixels."""
    num = den = 0.0
    for i, y, x, c in pixels(labels):
        num += weight(c) * per_pixel(log_softmax_at(logits, i, y, x), c, (i, y, x))
        den += weight(c)
    return num / den


def value(loss, logits, labels, priors=None) -> float:
    return batch_mean(loss(logits, labels, priors))[0].item()


def test_cross_entropy_is_the_mean_negative_log_likelihood():
    logits, labels = batch()
    want = reference(logits, labels, lambda lp, c, _: -lp[c])
    assert value(CrossEntropy(), logits, labels) == pytest.approx(want, rel=1e-12)
    torch_ce = F.cross_entropy(logits, labels, ignore_index=255).item()
    assert value(CrossEntropy(), logits, labels) == pytest.approx(torch_ce, rel=1e-12)


def test_weighted_cross_entropy_given_and_from_a_cost_matrix():
    logits, labels = batch()
    weights = [0.5, 2.0, 4.0, 1.5]
    loss = WeightedCrossEntropy(weights=weights)
    loss.for_classes(CLASSES)
    want = reference(logits, labels, lambda lp, c, _: -lp[c], weight=lambda c: weights[c])
    assert value(loss, logits, labels) == pytest.approx(want, rel=1e-12)
    torch_ce = F.cross_entropy(
        logits, labels, weight=torch.tensor(weights, dtype=torch.float64), ignore_index=255
    )
    assert value(loss, logits, labels) == pytest.approx(torch_ce.item(), rel=1e-6)
    # from the altruistic matrix: the mean cost of missing each class, normalised to mean 1
    cost = load_cost("altruistic")
    missing = [sum(cost[k, j].item() for k in range(19) if k != j) / 18 for j in range(19)]
    expected = [m / (sum(missing) / 19) for m in missing]
    assert cost_weights(cost).tolist() == pytest.approx(expected, rel=1e-12)
    from_cost = WeightedCrossEntropy(cost="altruistic")
    from_cost.for_classes(CLASS_NAMES)
    person = CLASS_NAMES.index("person")
    assert from_cost.weights[person].item() == pytest.approx(expected[person], rel=1e-6)
    assert from_cost.weights[person] > 4 * from_cost.weights[0]  # missing a person costs more


@pytest.mark.parametrize("gamma", [0.5, 2.0])
def test_focal_loss_down_weights_confident_pixels(gamma):
    logits, labels = batch()
    want = reference(logits, labels, lambda lp, c, _: -((1 - math.exp(lp[c])) ** gamma) * lp[c])
    assert value(FocalLoss(gamma), logits, labels) == pytest.approx(want, rel=1e-10)


@pytest.mark.parametrize("kind", ["global", "pixel"])
def test_logit_adjusted_cross_entropy_adds_tau_log_priors(kind):
    logits, labels = batch()
    g = torch.Generator().manual_seed(1)
    shape = (N,) if kind == "global" else (N, 3, 5)
    priors = torch.rand(shape, generator=g, dtype=torch.float64) + 0.05
    priors /= priors.sum(0)
    tau = 0.7

    def adjusted_nll(_, c, where):
        i, y, x = where
        pi = priors if kind == "global" else priors[:, y, x]
        z = logits.clone()
        z[i, :, y, x] += tau * pi.log()
        return -log_softmax_at(z, i, y, x)[c]

    want = reference(logits, labels, adjusted_nll)
    assert value(LogitAdjustedCrossEntropy(tau, kind), logits, labels, priors) == pytest.approx(
        want, rel=1e-12
    )


def test_expected_cost_term_of_a_cost_file(tmp_path):
    logits, labels = batch()
    matrix = [[0, 1, 8, 2], [1, 0, 8, 2], [3, 3, 0, 2], [1, 1, 8, 0]]
    path = tmp_path / "cost.yaml"
    path.write_text(yaml.safe_dump({"classes": list(CLASSES), "matrix": matrix}))
    lam = 0.3
    mean_off = sum(matrix[k][j] for k in range(N) for j in range(N) if k != j) / (N * (N - 1))

    def per_pixel(lp, c, _):
        expected = sum(math.exp(lp[k]) * matrix[k][c] / mean_off for k in range(N))
        return -lp[c] + lam * expected

    loss = ExpectedCostCrossEntropy(str(path), lam)
    loss.for_classes(CLASSES)
    got, terms = batch_mean(loss(logits, labels))
    assert got.item() == pytest.approx(reference(logits, labels, per_pixel), rel=1e-6)
    ce = reference(logits, labels, lambda lp, c, _: -lp[c])
    assert terms["cross_entropy"].item() == pytest.approx(ce, rel=1e-6)
    assert (got - terms["cross_entropy"]).item() == pytest.approx(
        lam * terms["expected_cost"].item(), rel=1e-6
    )


def test_zero_gamma_and_zero_tau_are_cross_entropy_bit_for_bit():
    logits, labels = batch(torch.float32)
    plain = batch_mean(CrossEntropy()(logits, labels))[0]
    assert torch.equal(batch_mean(FocalLoss(0.0)(logits, labels))[0], plain)
    priors = torch.tensor([0.1, 0.2, 0.3, 0.4])
    adjusted = LogitAdjustedCrossEntropy(0.0, "global")(logits, labels, priors)
    assert torch.equal(batch_mean(adjusted)[0], plain)


def make_losses():
    weighted = WeightedCrossEntropy(weights=[0.5, 2.0, 4.0, 1.5])
    expected = ExpectedCostCrossEntropy("robotistic", 0.5)
    for loss in (weighted, expected):
        loss.for_classes(CLASSES)
    return [CrossEntropy(), weighted, FocalLoss(2.0), LogitAdjustedCrossEntropy(1.0), expected]


def test_gradients_agree_with_finite_differences():
    logits, labels = batch()
    logits = logits[:, :, :2, :3].clone().requires_grad_()
    labels = labels[:, :2, :3]
    priors = torch.tensor([0.4, 0.3, 0.2, 0.1], dtype=torch.float64)
    for loss in make_losses():
        assert torch.autograd.gradcheck(
            lambda z, loss=loss: batch_mean(loss(z, labels, priors))[0], (logits,)
        ), type(loss).__name__


def test_a_batch_without_valid_pixels_gives_zero_not_nan():
    logits, labels = batch()
    labels[:] = 255
    for loss in make_losses():
        got, terms = batch_mean(loss(logits, labels, torch.full((N,), 0.25)))
        assert got.item() == 0 and all(t.item() == 0 for t in terms.values())


def test_settings_that_cannot_train_are_refused_in_one_line():
    with pytest.raises(ValueError, match="either weights or cost"):
        WeightedCrossEntropy()
    with pytest.raises(ValueError, match="4 positive numbers"):
        WeightedCrossEntropy(weights=[1.0, 2.0]).for_classes(CLASSES)
    with pytest.raises(ValueError, match="4 positive numbers"):
        WeightedCrossEntropy(weights=[1.0, 2.0, 0.0, 1.0]).for_classes(CLASSES)
    with pytest.raises(ValueError, match="gamma must be >= 0"):
        FocalLoss(-1.0)
    with pytest.raises(ValueError, match="'global' or 'pixel'"):
        LogitAdjustedCrossEntropy(1.0, "image")
    with pytest.raises(ValueError, match="lam must be >= 0"):
        ExpectedCostCrossEntropy("altruistic", -1.0)
    with pytest.raises(ValueError, match="unknown cost"):
        ExpectedCostCrossEntropy("selfish").for_classes(CLASSES)


def test_a_defer_row_is_refused_for_the_expected_cost(tmp_path):
    path = tmp_path / "defer.yaml"
    path.write_text(yaml.safe_dump({"off_diagonal": 1, "defer": 0.3}))
    with pytest.raises(ValueError, match="defer row"):
        ExpectedCostCrossEntropy(str(path)).for_classes(CLASSES)


def tiny_module(loss) -> SegmentationModule:
    net = DeepLabV3Plus(num_classes=19, backbone="resnet18", decoder_channels=8)
    return SegmentationModule(net, loss=loss)


def test_the_module_records_the_loss_and_gives_it_the_priors_it_asks_for():
    module = tiny_module(LogitAdjustedCrossEntropy(0.5, "pixel"))
    assert module.hparams["loss"] == {
        "class_path": "costseg.training.losses.LogitAdjustedCrossEntropy",
        "init_args": {"tau": 0.5, "priors": "pixel"},
    }
    with pytest.raises(ValueError, match="needs the training priors"):
        module.loss_priors((4, 6))
    priors = torch.rand(19, 4, 6, generator=torch.Generator().manual_seed(0))
    module.priors = priors / priors.sum(0)
    mirrored = (module.priors + module.priors.flip(-1)) / 2  # training flips half the images
    torch.testing.assert_close(module.loss_priors((4, 6)), mirrored / mirrored.sum(0))
    with pytest.raises(ValueError, match="use priors: global"):
        module.loss_priors((4, 4))
    module = tiny_module(LogitAdjustedCrossEntropy(0.5, "global"))
    module.priors = priors / priors.sum(0)
    torch.testing.assert_close(module.loss_priors((9, 9)), module.priors.mean((1, 2)))
    assert tiny_module(None).hparams["loss"]["class_path"].endswith(".CrossEntropy")
    assert tiny_module(None).loss_priors((4, 6)) is None
