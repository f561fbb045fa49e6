"""Meta classification and fusion (docs/definitions.md §15): the heat maps against a loop over
pixels, the scores against sklearn.metrics, the saved models read back, and the fused label
maps against a NumPy loop over segments written from the definition."""

from __future__ import annotations

import collections
import math

import numpy as np
import pytest
import torch
from scipy import ndimage
from sklearn.metrics import accuracy_score, r2_score, roc_auc_score

from costseg.costs import load_cost
from costseg.meta.fusion import FusedRules, fused_labels
from costseg.meta.heat_maps import EPSILON, heat_maps
from costseg.meta.models import fit_models, load_models, save_models, scores
from costseg.rules import Rule, apply_rules


def _probs(seed: int, n: int = 4, h: int = 6, w: int = 7) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return (3 * torch.randn(1, n, h, w, generator=g)).softmax(1)


def test_heat_maps_equal_a_loop_over_pixels() -> None:
    probs, n = _probs(0, n=19), 19
    cost = load_cost("altruistic")
    priors = torch.rand(n, 6, 7, generator=torch.Generator().manual_seed(1)) + 0.05
    expected_entropy = torch.rand(1, 6, 7, dtype=torch.float64) * 0.1
    ml = heat_maps(probs, Rule("ml", None, 1.0), priors, expected_entropy)
    maps = heat_maps(probs, Rule("altruistic", cost))
    off = max(cost[i, j].item() for i in range(n) for j in range(n) if i != j)
    for y in range(6):
        for x in range(7):
            p = [probs[0, k, y, x].item() for k in range(n)]
            e = sum(q * math.log(q + EPSILON) for q in p) / math.log(1 / n)
            top = sorted(p, reverse=True)
            expected = sorted(sum(cost[d, k].item() * p[k] for k in range(n)) for d in range(n))
            assert maps["E"][0, y, x].item() == pytest.approx(e, rel=1e-5)
            assert maps["D"][0, y, x].item() == pytest.approx(1 - top[0] + top[1], abs=1e-6)
            assert maps["R"][0, y, x].item() == pytest.approx((expected[1] - expected[0]) / off)
            q = sorted(p[k] / priors[k, y, x].item() for k in range(n))  # symmetric on p / π
            assert ml["R"][0, y, x].item() == pytest.approx(q[-1] - q[-2], rel=1e-5)
            h = -sum(v * math.log(v) for v in p if v > 0)
            mi = max(h - expected_entropy[0, y, x].item(), 0)
            assert ml["MI"][0, y, x].item() == pytest.approx(mi, abs=1e-5)


def _columns(seed: int, n: int = 300) -> dict[str, np.ndarray]:
    """Segments whose IoU depends on two features, with noise."""
    rng = np.random.default_rng(seed)
    e, s = rng.random(n), rng.random(n)
    iou = np.clip(1 - 0.7 * e + 0.2 * s + 0.1 * rng.standard_normal(n), 0, 1)
    return {"E": e, "S": s, "noise": rng.random(n), "iou": iou, "iou0": (iou < 0.3).astype(int)}


def test_scores_equal_sklearn_metrics_and_survive_a_round_trip(tmp_path) -> None:
    fit, test = _columns(0), _columns(1)
    models = fit_models(fit, ["E", "S", "noise"], num_images=10)
    got = scores(models, test)
    for name in ("logistic", "gradient_boosting", "entropy"):
        p = models.false_probability(name, test)
        iou = models.predicted_iou(name, test)
        assert got[name]["auroc"] == pytest.approx(roc_auc_score(test["iou0"], p))
        assert got[name]["accuracy"] == pytest.approx(accuracy_score(test["iou0"], p >= 0.5))
        assert got[name]["r2"] == pytest.approx(r2_score(test["iou"], iou))
        assert got[name]["sigma"] == pytest.approx(np.sqrt(np.mean((iou - test["iou"]) ** 2)))
        assert got[name]["segments"] == 300
    assert got["logistic"]["auroc"] > got["entropy"]["auroc"] > 0.5  # S helps; E alone helps
    save_models(tmp_path / "m.joblib", {"ml": models})
    again = load_models(tmp_path / "m.joblib")["ml"]
    assert scores(again, test) == got
    (tmp_path / "m.joblib").write_bytes((tmp_path / "m.joblib").read_bytes() + b"\0")
    with pytest.raises(ValueError, match="SHA-256"):
        load_models(tmp_path / "m.joblib")


def test_one_kind_of_segment_fits_no_model() -> None:
    columns = _columns(0)
    columns["iou0"] = np.zeros_like(columns["iou0"])
    models = fit_models(columns, ["E", "S"], num_images=1)
    assert models.fitted == {} and math.isnan(scores(models, _columns(1))["logistic"]["auroc"])


def _fused_by_loop(base, rule, false, classes, tau):
    """The fusion of docs/definitions.md §15 by a loop over R's segments (scipy's labelling)."""
    out = base.copy()
    for k in classes:
        components, count = ndimage.label(rule == k, structure=np.ones((3, 3)))
        for c in range(1, count + 1):
            segment = components == c
            candidate = not (base[segment] == k).any()
            if candidate and false[(k, c)] >= tau:
                continue
            out[segment] = k
    return out


def test_fused_labels_equal_a_loop_over_segments() -> None:
    rng = np.random.default_rng(3)
    for trial in range(20):
        h, w = 9, 11
        base = rng.integers(0, 3, (h, w))
        rule = np.where(rng.random((h, w)) < 0.4, 2, base)  # R adds class-2 pixels
        rule = np.where(rng.random((h, w)) < 0.1, 1, rule)
        # R's segments over all classes, numbered by first pixel (as segment_features does)
        ids = np.zeros((h, w), np.int64)
        false, n = {}, 0
        for k in range(3):
            components, count = ndimage.label(rule == k, structure=np.ones((3, 3)))
            for c in range(1, count + 1):
                n += 1
                ids[components == c] = n
                false[(k, c)] = rng.random()
        order = np.unique(ids.ravel(), return_index=True)[1]
        first = ids.ravel()[np.sort(order)]  # ids in order of first pixel
        renumber = np.zeros(n + 1, np.int64)
        renumber[first] = np.arange(1, n + 1)
        by_segment = np.zeros(n)
        position = 0
        for k in range(3):
            components, count = ndimage.label(rule == k, structure=np.ones((3, 3)))
            for c in range(1, count + 1):
                position += 1
                by_segment[renumber[position] - 1] = false[(k, c)]
        taus = (0.0, 0.3, 0.7, 1.01)
        got = fused_labels(base, rule, renumber[ids], by_segment, [2], taus)
        for t, tau in enumerate(taus):
            expected = _fused_by_loop(base, rule, false, [2], tau)
            np.testing.assert_array_equal(got[t], expected, err_msg=f"trial {trial}, τ {tau}")
        np.testing.assert_array_equal(got[-1], np.where(rule == 2, 2, base))  # nothing dropped


class _Constant:
    """Meta models whose classifier calls every segment false with one probability."""

    def __init__(self, p: float) -> None:
        self.p, self.fitted = p, {"gradient_boosting": None}

    def false_probability(self, model, columns):
        return np.full(len(columns["S"]), self.p)


def test_the_fused_rules_drop_the_candidates_the_classifier_distrusts() -> None:
    probs = _probs(5, n=19, h=16, w=24)
    priors = torch.rand(19, 16, 24, generator=torch.Generator().manual_seed(2)) + 0.05
    base, ml = Rule("robotistic", None), Rule("ml", None, 1.0)
    labels = apply_rules(probs, (base, ml), priors)[0].numpy()
    person = 11
    distrusted = collections.defaultdict(lambda: 0.9)  # every candidate dropped
    kept = _fused_by_loop(labels[0], labels[1], distrusted, [person], 0.5)
    assert (kept != labels[0]).any() and (
        kept != np.where(labels[1] == person, person, labels[0])
    ).any()
    for p, expected in ((0.9, kept), (0.1, np.where(labels[1] == person, person, labels[0]))):
        fused = FusedRules(base, (ml,), (0.5,), (person,)).using({"ml": _Constant(p)})
        np.testing.assert_array_equal(fused(probs, priors)[0, 0].numpy(), expected)
