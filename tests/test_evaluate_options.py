"""`evaluate.py --vertex_scaling mean`, `--calibrate vector` and `--guarantee_method
fixed_sequence` end to end, each against loops written out here: the cost matrices mixed by hand,
the scaling applied by hand, the Learn-then-Test p-values and the fixed sequence walked by hand."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch
from scipy.stats import binom

from costseg.checkpoints import find_checkpoint
from costseg.cli import evaluate_main
from costseg.costs import load_cost
from costseg.data.datamodule import StreetScenesDataModule
from costseg.decision import decide_reference

VERTICES = ["robotistic", "altruistic", "egoistic"]
GRID = [(1.0, 0.0, 0.0), (0.5, 0.5, 0.0), (0.5, 0.0, 0.5), (0.0, 1.0, 0.0), (0.0, 0.5, 0.5),
        (0.0, 0.0, 1.0)]  # fmt: skip
"""The --sweep 0.5 grid, in its order: α descending, then β descending."""
RUN = ["--no-progress", "--num_examples", "0", "--batch_size", "1"]


@pytest.fixture(scope="module")
def ckpt(tiny_run) -> str:
    return str(find_checkpoint(None, runs_dir=tiny_run[2]))


@pytest.fixture(scope="module")
def module(ckpt):
    from costseg.training.module import SegmentationModule

    return SegmentationModule.load_from_checkpoint(ckpt, map_location="cpu").eval()


def _split(name: str, length: int) -> list:
    """The tiny run's (image, label) pairs of a split, as the checkpoint's data config makes
    them (conftest.TINY_TRAIN), without augmentation."""
    data = StreetScenesDataModule(batch_size=2, num_workers=0, size=(64, 128), train_length=8,
                                  val_length=3, test_length=2, prior_images=4)  # fmt: skip
    scenes = data.make_dataset(name, augment=False)
    assert len(scenes) == length
    return [scenes[i] for i in range(length)]


def _saved(out: Path, stem: str) -> torch.Tensor:
    return torch.from_numpy(np.load(out / "probs" / f"{stem}.npz")["probs"]).float()[None]


def _mix(costs: list[torch.Tensor], w: tuple[float, float, float]) -> torch.Tensor:
    return (w[0] * costs[0] + w[1] * costs[1]) + w[2] * costs[2]


def _counts(pred: torch.Tensor, label: torch.Tensor, cls: int) -> tuple[int, int, int]:
    """(TP, FP, FN) pixels of ``cls`` by a loop over the labelled pixels."""
    tp = fp = fn = 0
    for p, y in zip(pred.flatten().tolist(), label.flatten().tolist(), strict=True):
        if y != 255:
            tp, fp, fn = tp + (p == y == cls), fp + (p == cls != y), fn + (y == cls != p)
    return tp, fp, fn


def test_vertex_scaling_mean_mixes_vertices_of_unit_mean_cost(ckpt, tmp_path):
    out = tmp_path / "out"
    args = ["--cost", "robotistic", "--sweep", "0.5", "--vertex_scaling", "mean", "--save-probs"]
    evaluate_main(["--ckpt_path", ckpt, *args, "--output_dir", str(out), *RUN])
    rows = json.loads((out / "sweep.json").read_text())["rows"]
    plain = [load_cost(n).double() for n in VERTICES]
    off = ~torch.eye(19, dtype=torch.bool)
    scaled = [c / (math.fsum(c[off].tolist()) / (19 * 18)) for c in plain]
    val = _split("val", 3)
    probs = [_saved(out, f"val_{i:06d}") for i in range(3)]
    differs = False
    for w in GRID:
        preds = [decide_reference(p, _mix(scaled, w))[0] for p in probs]
        differs |= any(
            not torch.equal(pred, decide_reference(p, _mix(plain, w))[0])
            for pred, p in zip(preds, probs, strict=True)
        )
        for cls, name in ((11, "person"), (2, "building")):
            counts = [_counts(pred, y, cls) for pred, (_, y) in zip(preds, val, strict=True)]
            tp, fp, fn = np.sum(counts, 0)
            row = next(r for r in rows if (r["alpha"], r["beta"], r["gamma"]) == w
                       and r["class"] == name and r["roi"] == 0)  # fmt: skip
            assert row["recall"] == (pytest.approx(tp / (tp + fn)) if tp + fn else None)
            assert row["precision"] == (pytest.approx(tp / (tp + fp)) if tp + fp else None)
    assert differs  # on these images the scaling changes decisions, so the rows prove it


def test_calibrate_vector_scales_the_reported_logits(ckpt, module, tmp_path):
    """a ⊙ z + b fitted on the first image of val; the other two are reported on softmax of it."""
    out = tmp_path / "out"
    rules = ["robotistic", "egoistic"]
    evaluate_main(["--ckpt_path", ckpt, "--cost", *rules, "--calibrate", "vector",
                   "--save-probs", "--output_dir", str(out), *RUN])  # fmt: skip
    scaling = json.loads((out / "calibration.json").read_text())["scaling"]
    assert scaling["kind"] == "vector" and len(set(scaling["scale"])) > 1
    a = torch.tensor(scaling["scale"], dtype=torch.float64)[:, None, None]
    b = torch.tensor(scaling["offset"], dtype=torch.float64)[:, None, None]
    assert sorted(p.stem for p in (out / "probs").glob("*.npz")) == ["val_000001", "val_000002"]
    val = _split("val", 3)
    with torch.no_grad():
        z = [module(image[None]).double()[0] for image, _ in val]
    nll = lambda p, y: -p.log().gather(0, y.clamp(max=18)[None])[0][y != 255].mean()  # noqa: E731
    fitted_on = val[0][1]
    assert nll((a * z[0] + b).softmax(0), fitted_on) < nll(z[0].softmax(0), fitted_on)
    confusion = json.loads((out / "results.json").read_text())["confusion_matrix"]
    for rule in rules:
        expected = np.zeros((19, 19), dtype=np.int64)
        for k in (1, 2):
            saved = _saved(out, f"val_{k:06d}")
            scaled = (a * z[k] + b).softmax(0)
            torch.testing.assert_close(saved[0].double(), scaled, atol=1e-3, rtol=0)
            pred, label = decide_reference(saved, load_cost(rule))[0], val[k][1]
            for p, y in zip(pred.flatten().tolist(), label.flatten().tolist(), strict=True):
                if y != 255:
                    expected[y, p] += 1
        assert np.array_equal(np.array(confusion[rule]), expected), rule


def _hoeffding_bentkus(risk: float, n: int, alpha: float) -> float:
    """LTT's Proposition 3, written out: min(exp(-n h1(R ∧ α, α)), e P(Bin(n, α) ≤ ⌈n R⌉))."""
    if n == 0:
        return 1.0
    r = min(risk, alpha)
    h1 = (r * math.log(r / alpha) if r > 0 else 0.0) + (1 - r) * math.log((1 - r) / (1 - alpha))
    return min(math.exp(-n * h1), math.e * binom.cdf(math.ceil(round(n * risk, 9)), n, alpha), 1)


def test_guarantee_fixed_sequence_walks_the_grid_until_the_first_failure(ckpt, module, tmp_path):
    """Per-image losses 1 - recall of sky on the 8 training images, p-values by hand, the
    grid walked in its order at level δ (no division by the family's size). The tiny model
    finds sky at the first grid point (robotistic) and hardly elsewhere: the walk stops."""
    out, delta, level, sky = tmp_path / "out", 0.1, 0.9, 10
    target = "sky:roi0:recall>=0.1"
    evaluate_main(["--ckpt_path", ckpt, "--cost", "robotistic", "--sweep", "0.5",
                   "--target", target, "--maximize", "sky:roi0:precision",
                   "--guarantee", str(delta), "--guarantee_method", "fixed_sequence",
                   "--calibration_split", "train", "--output_dir", str(out), *RUN])  # fmt: skip
    record = json.loads((out / "guarantee.json").read_text())
    assert record["method"] == "fixed_sequence" and record["calibration_images"] == 8
    costs = [load_cost(n).double() for n in VERTICES]
    losses, pooled = [], []
    with torch.no_grad():
        for image, label in _split("train", 8):
            probs = module(image[None]).double().softmax(1)
            counts = [_counts(decide_reference(probs, _mix(costs, w))[0], label, sky) for w in GRID]
            losses.append([fn / (tp + fn) if tp + fn else math.nan for tp, _, fn in counts])
            pooled.append(counts)
    certified = []
    for k, w in enumerate(GRID):
        column = [row[k] for row in losses if not math.isnan(row[k])]
        if _hoeffding_bentkus(sum(column) / max(len(column), 1), len(column), level) > delta:
            break
        certified.append(w)
    assert 0 < len(certified) < len(GRID)  # the walk certified a point and then stopped
    got = [(c["alpha"], c["beta"], c["gamma"]) for c in record["certified"]]
    assert got == certified
    assert record["found"] == bool(certified)
    if certified:  # the best pooled road precision among the certified points
        tp, fp, _ = np.sum(pooled, 0).T  # (6,) each: pooled over the images
        precision = {w: tp[k] / (tp[k] + fp[k]) for k, w in enumerate(GRID) if tp[k] + fp[k]}
        best = max((w for w in certified if w in precision), key=precision.get)
        chosen = record["chosen"]
        assert (chosen["alpha"], chosen["beta"], chosen["gamma"]) == best
