"""The pieces of ``--defer_sweep`` against independent references: the defer costs, the group,
risk–coverage (a loop over pixels, a hand-computed AURC), the all-class coverage, the ties to
the larger defer cost, and fixed-sequence testing along several paths (a NumPy walk)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from test_guarantee import reference_hb

from costseg.calibration.guarantee import fixed_sequences, learn_then_test
from costseg.classes import CLASS_NAMES
from costseg.costs import load_cost, save_cost, symmetric_cost, with_defer
from costseg.decision.label_maps import DEFERRED
from costseg.metrics import RoIPrecisionRecall
from costseg.metrics.functional.deferral import risk_coverage_area, selective_error
from costseg.metrics.per_image import per_image_counts
from costseg.metrics.selection import best_points, parse_metric, parse_target
from costseg.report.results import GroupResult
from costseg.report.risk_coverage import curve
from costseg.rules import defer_costs, defer_group

N = len(CLASS_NAMES)


def test_defer_costs_and_their_refusals() -> None:
    assert defer_costs(0, 0.3, 0.1) == [0.0, 0.1, 0.2, 0.3]
    assert defer_costs(0.25, 1, 0.5) == [0.25, 0.75]  # STOP not on the grid: left out
    assert defer_costs(0, 1, 0.01)[-1] == 1 and len(defer_costs(0, 1, 0.01)) == 101
    for bad, needle in [
        ((0.5, 0.5, 0.1), "START < STOP"),
        ((0.6, 0.5, 0.1), "START < STOP"),
        ((0, 1, 0), "STEP > 0"),
        ((0, 1, 2), "one defer cost"),
        ((0, 1, 0.001), "at most 101"),
        ((0, math.inf, 1), "finite"),
    ]:
        with pytest.raises(ValueError, match=needle):
            defer_costs(*bad)


def test_defer_group_is_every_rule_at_every_cost(tmp_path) -> None:
    group = defer_group(["robotistic", "ml"], [0.0, 0.5, 1.0])
    assert group.paths == ((0, 1, 2), (3, 4, 5)) and group.prefer == (0.0, 0.5, 1.0) * 2
    assert group.names[4] == "ml@defer=0.5" and group.columns[4] == {"matrix": "ml", "defer": 0.5}
    robotistic = load_cost("robotistic")
    assert torch.equal(group.cost(2), with_defer(robotistic, 1.0)) and group.cost(3) is None
    assert group.rules[4].priors_alpha == 1 and group.candidates and group.needs_priors
    own = tmp_path / "chow.yaml"
    save_cost(own, with_defer(symmetric_cost(N), 0.2), "chow")
    with pytest.raises(ValueError, match="defer row of its own"):
        defer_group([str(own)], [0.0, 0.5])
    with pytest.raises(ValueError, match="ascending"):
        defer_group(["robotistic"], [0.5, 0.5])


def test_risk_coverage_area_by_hand() -> None:
    # sorted by coverage: (0.2, 0.1), (0.6, 0.3), (1, 0.5): 0.4 * 0.2 + 0.4 * 0.4 = 0.24
    area = risk_coverage_area([1.0, 0.2, float("nan"), 0.6], [0.5, 0.1, 0.9, 0.3])
    assert area == pytest.approx(0.24, abs=1e-15)
    assert math.isnan(risk_coverage_area([0.5, float("nan")], [0.1, 0.2]))  # one point left
    assert risk_coverage_area([0.5, 0.5], [0.1, 0.4]) == 0  # no width


def test_selective_error_is_one_minus_accuracy_of_the_kept_pixels() -> None:
    cm = torch.randint(0, 50, (4, 3, 5, 5))
    want = 1 - np.trace(cm.numpy(), axis1=-2, axis2=-1) / cm.numpy().sum((-2, -1))
    np.testing.assert_allclose(selective_error(cm).numpy(), want, rtol=1e-12)


def _brute_force(probs, target, roi, cost: np.ndarray):
    """Label per pixel by a Python loop over pixels: argmin over the N + 1 rows, ties first."""
    b, _, h, w = probs.shape
    out = np.empty((b, h, w), np.int64)
    for i in range(b):
        for y in range(h):
            for x in range(w):
                risks = cost @ probs[i, :, y, x]
                best = min(range(len(risks)), key=lambda r, risks=risks: (risks[r], r))
                out[i, y, x] = DEFERRED if best == cost.shape[1] else best
    return out


@pytest.mark.parametrize("seed", [0, 1])
def test_the_curve_equals_a_loop_over_pixels(seed: int) -> None:
    gen = torch.Generator().manual_seed(seed)
    logits = 3 * torch.randn(2, N, 6, 7, generator=gen, dtype=torch.float64)
    probs = logits.softmax(1)
    target = probs.argmax(1)  # most pixels right, some not: a noisy copy
    flip = torch.rand(target.shape, generator=gen) < 0.3
    target[flip] = torch.randint(0, N, target.shape, generator=gen)[flip]
    target[0, 0, :3] = 255
    roi = torch.randint(0, 3, (6, 7), generator=gen)
    costs = [0.0, 0.2, 0.45, 0.9]
    group = defer_group(["robotistic", "egoistic"], costs)
    metric = RoIPrecisionRecall(N, len(group.names), 2)
    metric.update(group.decide(probs, None), target, roi)
    result = GroupResult(group, metric.compute(), {})
    p, t, r = probs.numpy(), target.numpy(), roi.numpy()
    valid = t != 255
    inside = lambda k: valid & ((r == k)[None] if k else True)  # noqa: E731
    for path, name in zip(group.paths, ("robotistic", "egoistic"), strict=True):
        preds = [_brute_force(p, t, r, with_defer(load_cost(name), c).numpy()) for c in costs]
        for k in range(3):
            m = inside(k)
            kept = [m & (pred != DEFERRED) for pred in preds]
            coverage, risk = curve(result, path, "all", k)
            np.testing.assert_allclose(coverage, [q.sum() / m.sum() for q in kept], rtol=1e-12)
            with np.errstate(invalid="ignore"):  # nothing kept: NaN
                wrong = [(q & (p != t)).sum() / q.sum() for q, p in zip(kept, preds, strict=True)]
            np.testing.assert_allclose(risk, wrong, rtol=1e-12)
            for cls in set(t[m].tolist()):
                g = m & (t == cls)
                coverage, risk = curve(result, path, cls, k)
                kept_c = [g & (pred != DEFERRED) for pred in preds]
                np.testing.assert_allclose(coverage, [q.sum() / g.sum() for q in kept_c])
                miss = [
                    (q & (pred != cls)).sum() / q.sum() if q.any() else np.nan
                    for q, pred in zip(kept_c, preds, strict=True)
                ]
                np.testing.assert_allclose(risk, miss, rtol=1e-12)
    coverage, _ = curve(result, group.paths[0], "all", 0)
    assert coverage[0] < coverage[-1]  # the sweep reaches from deferring to deciding


def test_all_classes_coverage_per_image_equals_a_count() -> None:
    gen = torch.Generator().manual_seed(3)
    preds = torch.randint(0, 4, (2, 3, 5, 6), generator=gen)
    preds[torch.rand(preds.shape, generator=gen) < 0.3] = DEFERRED
    target = torch.randint(0, 4, (2, 5, 6), generator=gen)
    target[:, 0] = 255
    roi = torch.randint(0, 3, (5, 6), generator=gen)
    counts = per_image_counts(preds, target, roi, None, 1, "coverage", num_rois=2)
    for i in range(2):
        inside = (target[i] != 255) & (roi == 1)
        for k in range(3):
            kept = (inside & (preds[i, k] != DEFERRED)).sum()
            assert counts[i, k].tolist() == [int(kept), int(inside.sum())]
    with pytest.raises(ValueError, match="only coverage"):
        per_image_counts(preds, target, roi, None, 1, "recall", num_rois=2)


def test_all_classes_in_targets_and_ties_to_the_larger_defer_cost() -> None:
    assert parse_metric("all:roi2:coverage") == (None, 2, "coverage")
    assert parse_target("all:roi1:coverage>=0.5").cls is None
    with pytest.raises(ValueError, match="only coverage"):
        parse_metric("all:roi1:recall")
    values, ok = torch.tensor([0.4, 0.8, 0.8, 0.8]), torch.tensor([True, True, True, False])
    assert best_points(values, ok, prefer=[0.0, 0.1, 0.3, 0.9]) == [2, 1]
    losses = np.zeros((50, 4))
    result = learn_then_test(losses, 0.2, 0.1)
    assert result.best([0.4, 0.8, 0.8, 0.8], prefer=[0.0, 0.1, 0.3, 0.2]) == 2


def _numpy_fixed_sequences(losses: np.ndarray, alpha: float, delta: float, paths) -> list[int]:
    """Walk each path at δ / len(paths), stopping at its first p-value above the level."""
    valid = []
    for path in paths:
        for j in path:
            n = len(losses)
            if reference_hb(int(losses[:, j].sum()), n, alpha) > delta / len(paths):
                break
            valid.append(j)
    return valid


def test_fixed_sequences_equals_a_numpy_walk() -> None:
    rng = np.random.default_rng(0)
    risks = np.array([0.01, 0.05, 0.12, 0.3, 0.02, 0.2, 0.04, 0.08])
    paths = [(0, 1, 2, 3), (4, 5, 6, 7)]  # path 2 stops at 5 although 6 and 7 are safe
    for _ in range(5):
        losses = (rng.random((120, 8)) < risks).astype(float)
        got = fixed_sequences(losses, 0.15, 0.1, paths)
        assert got.valid.tolist() == _numpy_fixed_sequences(losses, 0.15, 0.1, paths)
        assert got.delta == 0.1 and got.method == "fixed_sequence"
    losses = np.zeros((100, 8))
    assert fixed_sequences(losses, 0.15, 0.1, paths).valid.tolist() == list(range(8))
    with pytest.raises(ValueError, match="disjoint"):
        fixed_sequences(losses, 0.15, 0.1, [(0, 1), (1, 2)])
