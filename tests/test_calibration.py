"""Temperature / vector scaling, the pixel sampler, and CalibrationError against references."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy.optimize import minimize_scalar
from torchmetrics.functional.classification import multiclass_calibration_error

from costseg.calibration.sample import PixelSampler
from costseg.calibration.scaling import (
    TEMPERATURE_RANGE,
    Scaling,
    fit_temperature,
    fit_vector_scaling,
)
from costseg.metrics import CalibrationError

# ---------------------------------------------------------------- ECE references and data


def brute_force_ece(probs, target, n_bins: int, norm: str) -> dict[str, object]:
    """docs/definitions.md §6 with Python loops: bins [b/n, (b+1)/n), 1.0 in the last bin, 255
    ignored."""
    pixels = []
    for b in range(target.shape[0]):
        for y in range(target.shape[1]):
            for x in range(target.shape[2]):
                if int(target[b, y, x]) != 255:
                    pixels.append((probs[b, :, y, x].tolist(), int(target[b, y, x])))

    def bin_of(v: float) -> int:
        return next((i for i in range(n_bins) if i / n_bins <= v < (i + 1) / n_bins), n_bins - 1)

    def gap(entries: list[tuple[float, bool]]) -> tuple[float, list[int], list[float]]:
        bins: list[list[tuple[float, bool]]] = [[] for _ in range(n_bins)]
        for value, hit in entries:
            bins[bin_of(value)].append((value, hit))
        total = sum(abs(sum(h for _, h in e) - sum(v for v, _ in e)) for e in bins)
        acc = [sum(h for _, h in e) / len(e) if e else math.nan for e in bins]
        return total / len(entries), [len(e) for e in bins], acc

    if norm == "top":
        entries = [(max(p), p.index(max(p)) == y) for p, y in pixels]
        ece, counts, acc = gap(entries)
        return {"ece": ece, "count": counts, "accuracy": acc}
    per_class = [gap([(p[k], y == k) for p, y in pixels]) for k in range(len(pixels[0][0]))]
    return {
        "ece": sum(g[0] for g in per_class) / len(per_class),
        "per_class": [g[0] for g in per_class],
        "count": [g[1] for g in per_class],
        "accuracy": [g[2] for g in per_class],
    }


def make_probs(seed: int = 0, shape=(3, 4, 5, 6)) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    b, n, h, w = shape
    probs = (2 * torch.randn(shape, generator=g)).softmax(1)
    target = torch.randint(0, n, (b, h, w), generator=g)
    target[torch.rand(b, h, w, generator=g) < 0.25] = 255
    probs[0, :, 0, :2] = 0.0
    probs[0, 0, 0, 0] = 1.0  # confidence exactly 1: the last bin
    probs[0, :3, 0, 1] = torch.tensor([0.5, 0.25, 0.25])  # exactly on bin edges (n_bins 4)
    target[0, 0, :2] = torch.tensor([0, 1])
    return probs, target


@pytest.mark.parametrize("norm", ["top", "class"])
@pytest.mark.parametrize("n_bins", [4, 15])
def test_ece_matches_brute_force(norm: str, n_bins: int) -> None:
    probs, target = make_probs()
    metric = CalibrationError(num_classes=4, n_bins=n_bins, norm=norm)
    for i in range(len(probs)):  # batch by batch
        metric.update(probs[i : i + 1], target[i : i + 1])
    got, want = metric.compute(), brute_force_ece(probs, target, n_bins, norm)
    assert got["ece"].dtype == torch.float64
    assert got["ece"].item() == pytest.approx(want["ece"], rel=1e-9, abs=1e-12)
    assert got["count"].tolist() == want["count"]
    torch.testing.assert_close(
        got["accuracy"], torch.tensor(want["accuracy"], dtype=torch.float64), equal_nan=True
    )
    assert (got["count"].reshape(-1, n_bins).sum(1) == (target != 255).sum()).all()
    if norm == "class":
        torch.testing.assert_close(got["per_class"], torch.tensor(want["per_class"]).double())
    torch.testing.assert_close(got["edges"], torch.linspace(0, 1, n_bins + 1).double())


def test_nll_brier_and_ece_per_predicted_class_equal_numpy_loops() -> None:
    """docs/definitions.md §13 with a loop over the labelled pixels in NumPy."""
    probs, target = make_probs(seed=3, shape=(2, 4, 6, 7))
    probs[1, :, 0, 0] = torch.tensor([0.0, 1.0, 0.0, 0.0])  # p_y = 0: the NLL's floor
    target[1, 0, 0] = 0
    metric = CalibrationError(num_classes=4, n_bins=15)
    for i in range(len(probs)):
        metric.update(probs[i : i + 1], target[i : i + 1])
    got = metric.compute()
    p = probs.double().numpy().transpose(0, 2, 3, 1).reshape(-1, 4)
    y = target.numpy().reshape(-1)
    nll, brier, by_class = [], [], {k: [] for k in range(4)}
    for pixel, label in zip(p, y, strict=True):
        if label == 255:
            continue
        nll.append(-np.log(max(pixel[label], 1e-12)))
        brier.append(sum((pixel[k] - (k == label)) ** 2 for k in range(4)))
        k = int(np.argmax(pixel))
        by_class[k].append((pixel[k], k == label))
    want = []
    for entries in by_class.values():
        bins = [[] for _ in range(15)]
        for value, hit in entries:
            bins[min(int(value * 15), 14)].append((value, hit))
        gaps = [abs(sum(h for _, h in b) - sum(v for v, _ in b)) for b in bins]
        want.append(sum(gaps) / len(entries) if entries else math.nan)
    assert got["nll"].item() == pytest.approx(np.mean(nll), rel=1e-6)
    assert np.mean(nll) > 27.6 / len(nll)  # the floored pixel counts
    assert got["brier"].item() == pytest.approx(np.mean(brier), rel=1e-6)
    torch.testing.assert_close(got["per_class"], torch.tensor(want).double(), equal_nan=True)
    assert got["classwise_ece"].item() == pytest.approx(np.nanmean(want))


def test_top_label_ece_agrees_with_torchmetrics() -> None:
    probs, target = make_probs(seed=1, shape=(2, 5, 16, 16))
    # torchmetrics gives p = 1 a bin of its own; keep such pixels out of this comparison.
    probs[0, :, 0, :2] = (2 * torch.randn(5, 2)).softmax(0)
    assert (probs < 1).all()
    metric = CalibrationError(num_classes=5, norm="top")
    metric.update(probs, target)
    reference = multiclass_calibration_error(probs, target, 5, n_bins=15, ignore_index=255)
    torch.testing.assert_close(metric.compute()["ece"].float(), reference, rtol=1e-5, atol=1e-7)


def test_bins_hand_case_and_ignored_pixels() -> None:
    metric = CalibrationError(num_classes=2, n_bins=2, norm="class")
    p0 = torch.tensor([0.9, 0.6, 0.3, 1.0, 0.7])
    probs = torch.stack([p0, 1 - p0]).reshape(1, 2, 5, 1)
    target = torch.tensor([0, 1, 1, 0, 255]).reshape(1, 5, 1)
    metric.update(probs, target)
    out = metric.compute()
    # Class 0: bin 0 holds 0.3 (miss), bin 1 holds 0.9, 0.6, 1.0 (hit, miss, hit); 0.7 ignored.
    # Class 1: bin 0 holds 0.1, 0.4, 0.0 (miss, hit, miss), bin 1 holds 0.7 (hit).
    assert out["count"].tolist() == [[1, 3], [3, 1]]
    gap0 = (abs(0 - 0.3) + abs(2 - 2.5)) / 4
    gap1 = (abs(1 - 0.5) + abs(1 - 0.7)) / 4
    torch.testing.assert_close(out["per_class"], torch.tensor([gap0, gap1]).double())
    assert out["ece"].item() == pytest.approx((gap0 + gap1) / 2)


def test_empty_metric_and_bad_inputs() -> None:
    metric = CalibrationError(num_classes=3)
    metric.update(torch.full((1, 3, 2, 2), 1 / 3), torch.full((1, 2, 2), 255))
    assert math.isnan(metric.compute()["ece"].item())
    with pytest.raises(ValueError, match="3 classes"):
        metric.update(torch.rand(1, 4, 2, 2), torch.zeros(1, 2, 2, dtype=torch.long))
    with pytest.raises(ValueError, match=r"got \(1, 3, 2, 2\) and \(1, 3, 2\)"):
        metric.update(torch.rand(1, 3, 2, 2), torch.zeros(1, 3, 2, dtype=torch.long))
    with pytest.raises(ValueError, match=r"target holds \[3\]"):
        metric.update(torch.rand(1, 3, 2, 2), torch.full((1, 2, 2), 3))
    with pytest.raises(ValueError, match="norm"):
        CalibrationError(num_classes=3, norm="l2")  # type: ignore[arg-type]


# ---------------------------------------------------- batches (DDP: tests/test_metrics_ddp.py)


def run_ece(batches: list[list[int]]) -> list[dict[str, torch.Tensor]]:
    probs, target = make_probs(seed=2, shape=(3, 4, 8, 8))
    metrics = [CalibrationError(4, n_bins=15, norm=norm) for norm in ("top", "class")]
    for metric in metrics:
        for batch in batches:
            metric.update(probs[batch], target[batch])
    return [metric.compute() for metric in metrics]


def test_batches_merge_exactly() -> None:
    # The same per-batch sums; two DDP processes: tests/test_metrics_ddp.py.
    expected = run_ece([[0], [1], [2]])
    for one_batch, batched in zip(run_ece([[0, 1, 2]]), expected, strict=True):
        torch.testing.assert_close(one_batch["count"], batched["count"], rtol=0, atol=0)
        torch.testing.assert_close(one_batch["ece"], batched["ece"], rtol=1e-12, atol=0)


# ---------------------------------------------------------------- temperature / vector scaling


def sample_labels(scores: torch.Tensor, seed: int) -> torch.Tensor:
    """One label per row drawn from softmax(scores)."""
    g = torch.Generator().manual_seed(seed)
    return torch.multinomial(scores.double().softmax(1), 1, generator=g)[:, 0]


def nll(logits: torch.Tensor, target: torch.Tensor, temperature: float) -> float:
    return torch.nn.functional.cross_entropy(logits.double() / temperature, target).item()


@pytest.mark.parametrize("true_t", [0.6, 1.7])
def test_temperature_recovers_the_generating_temperature(true_t: float) -> None:
    # 200 000 pixels, 5 classes: the estimate's standard error is well under 1 %; allow 3 %.
    z = 3 * torch.randn(200_000, 5, generator=torch.Generator().manual_seed(0))
    y = sample_labels(z / true_t, seed=1)
    assert fit_temperature(z, y) == pytest.approx(true_t, rel=0.03)


def test_temperature_is_the_nll_minimum() -> None:
    g = torch.Generator().manual_seed(3)
    z, y = 2 * torch.randn(5000, 6, generator=g), torch.randint(0, 6, (5000,), generator=g)
    y[:2000] = z[:2000].argmax(1)  # partly informative logits
    t = fit_temperature(z, y)
    reference = minimize_scalar(
        lambda s: nll(z, y, math.exp(s)), bounds=(-3, 3), method="bounded", options={"xatol": 1e-9}
    )
    assert t == pytest.approx(math.exp(reference.x), rel=1e-4)
    assert nll(z, y, t) <= min(nll(z, y, t * 1.001), nll(z, y, t / 1.001))


def test_temperature_shapes_ignore_and_bounds() -> None:
    g = torch.Generator().manual_seed(4)
    logits, target = (
        torch.randn(2, 3, 6, 7, generator=g),
        torch.randint(0, 3, (2, 6, 7), generator=g),
    )
    flat = fit_temperature(logits.movedim(1, -1).reshape(-1, 3), target.reshape(-1))
    assert fit_temperature(logits, target) == pytest.approx(flat, rel=1e-12)
    noisy_logits, noisy_target = logits.clone(), target.clone()
    noisy_logits[:, :, 0], noisy_target[:, 0] = 50 * torch.randn(2, 3, 7, generator=g), 255
    kept = fit_temperature(logits[:, :, 1:], target[:, 1:])
    assert fit_temperature(noisy_logits, noisy_target) == pytest.approx(kept, rel=1e-12)
    separable = torch.tensor([[1.0, 0.0], [0.0, 1.0]])
    assert fit_temperature(separable, torch.tensor([0, 1])) == TEMPERATURE_RANGE[0]
    with pytest.raises(ValueError, match=r"target \(B, H, W\)"):
        fit_temperature(logits, target[0])
    with pytest.raises(ValueError, match="no pixel"):
        fit_temperature(logits, torch.full_like(target, 255))
    with pytest.raises(ValueError, match=r"target holds \[7\]"):
        fit_temperature(logits, torch.full_like(target, 7))


def test_vector_scaling_recovers_scale_and_offset() -> None:
    z = 2 * torch.randn(300_000, 3, generator=torch.Generator().manual_seed(5))
    a_true, b_true = torch.tensor([0.5, 1.0, 2.0]), torch.tensor([0.5, -0.3, -0.2])
    y = sample_labels(a_true * z + b_true, seed=6)
    a, b = fit_vector_scaling(z, y)
    assert a.dtype == b.dtype == torch.float64 and abs(b.sum()) < 1e-9
    torch.testing.assert_close(a, a_true.double(), atol=0.05, rtol=0)
    torch.testing.assert_close(b, b_true.double(), atol=0.05, rtol=0)
    # On such data no single temperature can fit: vector scaling's NLL is clearly lower.
    t = fit_temperature(z, y)
    vector_nll = torch.nn.functional.cross_entropy(a * z.double() + b, y).item()
    assert vector_nll < nll(z, y, t) - 0.01


def test_vector_scaling_with_an_absent_class() -> None:
    g = torch.Generator().manual_seed(7)
    z = torch.randn(3000, 4, generator=g)
    y = sample_labels(z[:, :3], seed=8)  # class 3 never occurs
    a, b = fit_vector_scaling(z, y)
    # Without evidence class 3 keeps the temperature's scale; its offset stays finite.
    assert torch.isfinite(a).all() and torch.isfinite(b).all()
    assert a[3].item() == pytest.approx(1 / fit_temperature(z, y), rel=1e-12)


def test_scaling_apply_describe_and_round_trip() -> None:
    z = torch.randn(2, 3, 4, 5)
    torch.testing.assert_close(Scaling().apply(z), z.softmax(1))
    t = Scaling("temperature", temperature=1.5, fitted_on="8 images")
    torch.testing.assert_close(t.apply(z), (z / 1.5).softmax(1))
    a, b = [0.5, 1.0, 2.0], [0.1, 0.0, -0.1]
    v = Scaling("vector", scale=torch.tensor(a), offset=b)
    expected = (torch.tensor(a).view(1, 3, 1, 1) * z + torch.tensor(b).view(1, 3, 1, 1)).softmax(1)
    torch.testing.assert_close(v.apply(z), expected)
    torch.testing.assert_close(v.apply(z[:, :, 0, 0]), expected[:, :, 0, 0])
    assert t.describe() == "temperature scaling, T = 1.500 (fitted on 8 images)"
    assert "no scaling" in Scaling().describe()
    assert "a in [0.500, 2.000]" in v.describe() and "b in [-0.100, 0.100]" in v.describe()
    for s in (Scaling(), t, v):
        assert Scaling(**s.to_dict()) == s
    with pytest.raises(ValueError, match="temperature must be"):
        Scaling("temperature", temperature=0.0)
    with pytest.raises(ValueError, match="lengths"):
        Scaling("vector", scale=[1.0], offset=[])
    with pytest.raises(ValueError, match="3 classes"):
        v.apply(torch.randn(2, 4))


# ---------------------------------------------------------------- the pixel sampler


def test_sampler_keeps_real_labelled_pixels_reproducibly() -> None:
    g = torch.Generator().manual_seed(9)
    logits, target = (
        torch.randn(4, 3, 6, 5, generator=g),
        torch.randint(0, 3, (4, 6, 5), generator=g),
    )
    target[torch.rand(4, 6, 5, generator=g) < 0.3] = 255
    target[3] = 255
    target[3, 0, 0] = 1  # one labelled pixel: kept, alone
    one, two = PixelSampler(pixels_per_image=7, seed=1), PixelSampler(pixels_per_image=7, seed=1)
    one.update(logits, target)
    two.update(logits[:1], target[:1])
    two.update(logits[1:], target[1:])
    assert one.num_images == 4 and one.num_pixels == 7 * 3 + 1
    for got, want in zip(one.tensors(), two.tensors(), strict=True):
        assert torch.equal(got, want)  # batching does not change the sample
    sample_logits, sample_target = one.tensors()
    assert (sample_target != 255).all()
    pixels = {
        (tuple(logits[i, :, y, x].tolist()), int(target[i, y, x]))
        for i in range(4) for y in range(6) for x in range(5) if target[i, y, x] != 255
    }  # fmt: skip
    rows = [(tuple(r.tolist()), int(t)) for r, t in zip(sample_logits, sample_target, strict=True)]
    assert set(rows) <= pixels and len(set(rows)) == len(rows)
    other = PixelSampler(pixels_per_image=7, seed=2)
    other.update(logits, target)
    assert not torch.equal(other.tensors()[0], sample_logits)


def test_sampler_is_uniform_over_labelled_pixels() -> None:
    target = torch.arange(20).reshape(1, 4, 5) % 3
    target[0, 0] = 255  # 15 labelled pixels; 5 of them drawn per image: each with p = 1/3
    logits = torch.arange(60.0).reshape(1, 3, 4, 5)
    sampler, draws = PixelSampler(pixels_per_image=5, seed=0), 3000
    for _ in range(draws):
        sampler.update(logits, target)
    hits = torch.bincount(sampler.tensors()[0][:, 0].long(), minlength=20).double() / draws
    assert (hits[:5] == 0).all()
    # Binomial(3000, 1/3) standard deviation 0.0086: 5 sigma.
    torch.testing.assert_close(hits[5:], torch.full((15,), 1 / 3).double(), atol=0.043, rtol=0)


def test_sampler_fit_matches_fit_on_all_pixels() -> None:
    g = torch.Generator().manual_seed(10)
    logits = 3 * torch.randn(6, 4, 40, 40, generator=g)
    y = sample_labels(logits.movedim(1, -1).reshape(-1, 4) / 1.4, seed=11).reshape(6, 40, 40)
    sampler = PixelSampler(pixels_per_image=1000)
    sampler.update(logits, y)
    scaling = sampler.fit("temperature")
    assert scaling.kind == "temperature" and "6 images, 6000 pixels" in scaling.describe()
    assert scaling.temperature == pytest.approx(fit_temperature(logits, y), rel=0.05)
    vector = sampler.fit("vector")
    assert vector.kind == "vector" and len(vector.scale) == 4
    assert sampler.fit("none") == Scaling()
    with pytest.raises(ValueError, match="empty"):
        PixelSampler().fit()
    with pytest.raises(ValueError, match="pixels_per_image"):
        PixelSampler(pixels_per_image=0)
