"""scripts/check_guarantee.py with --defer_sweep on the tiny checkpoint: its Learn-then-Test and
naive choices equal a NumPy recomputation from the per-image counts it saved (fixed-sequence
along each rule from its smallest defer cost at δ / rules, ties to the larger defer cost)."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import numpy as np

from costseg.calibration.guarantee import hoeffding_bentkus_pvalue
from costseg.checkpoints import find_checkpoint

SCRIPT = Path(__file__).resolve().parents[1] / "scripts" / "check_guarantee.py"
COSTS = [0.0, 0.5, 1.0]
ALPHA, DELTA = 0.5, 0.5  # target handled_recall >= 0.5


def _script():
    spec = importlib.util.spec_from_file_location("check_guarantee", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _expected(target: np.ndarray, goal: np.ndarray) -> tuple[int | None, int | None]:
    """(LTT's choice, the naive choice) on (n, K, 2) counts, written out in NumPy."""
    with np.errstate(invalid="ignore", divide="ignore"):
        losses = 1 - target[..., 0] / target[..., 1]  # NaN: no person pixel in the RoI
        objective = goal[..., 0].sum(0) / goal[..., 1].sum(0)
        pooled_target = target[..., 0].sum(0) / target[..., 1].sum(0)
    valid = []
    for path in (range(0, 3), range(3, 6)):  # robotistic, egoistic: smallest defer cost first
        for j in path:
            kept = losses[~np.isnan(losses[:, j]), j]
            p = hoeffding_bentkus_pvalue(kept.mean() if len(kept) else 0.0, len(kept), ALPHA)
            if p > DELTA / 2:
                break
            valid.append(j)
    prefer = COSTS * 2

    def best(points):
        points = [j for j in points if not np.isnan(objective[j])]
        return max(points, key=lambda j: (objective[j], prefer[j])) if points else None

    return best(valid), best(np.flatnonzero(pooled_target >= 1 - ALPHA).tolist())


def test_the_defer_sweep_choices_equal_a_numpy_recomputation(tiny_run, tmp_path) -> None:
    ckpt = find_checkpoint(None, runs_dir=tiny_run[2])
    out = tmp_path / "check"
    args = ["--ckpt_path", str(ckpt), "--defer_sweep", "0", "1", "0.5"]
    args += ["--cost", "robotistic", "egoistic", "--guarantee_method", "fixed_sequence"]
    args += ["--target", "person:roi0:handled_recall>=0.5", "--maximize", "all:roi0:coverage"]
    args += ["--guarantee", str(DELTA), "--n", "6", "--trials", "1", "--test", "4"]
    args += ["--batch_size", "5", "--output_dir", str(out), "--device", "cpu"]
    assert _script().main(args) == 0
    record = json.loads((out / "guarantee_check.json").read_text())
    assert [c["defer"] for c in record["candidates"]] == COSTS * 2
    with np.load(out / "counts.npz") as counts:
        target, goal = counts["target"][4:], counts["maximize"][4:]  # the calibration set
    ltt, naive = _expected(target, goal)
    assert record["ltt"]["chosen"] == [ltt] and record["naive"]["chosen"] == [naive]
    assert ltt is not None  # the check certifies something


def test_under_shift_the_clean_choices_are_tested_on_shifted_images(tiny_run, tmp_path) -> None:
    """The calibration sets stay clean (the same choices); the violation rate on the test images
    seen through the shift equals a NumPy recomputation from the saved shifted counts."""
    ckpt = find_checkpoint(None, runs_dir=tiny_run[2])
    out = tmp_path / "check"
    args = ["--ckpt_path", str(ckpt), "--defer_sweep", "0", "1", "0.5"]
    args += ["--cost", "robotistic", "egoistic", "--target", "person:roi0:handled_recall>=0.5"]
    args += ["--maximize", "all:roi0:coverage", "--guarantee", str(DELTA), "--n", "4"]
    args += ["--trials", "3", "--test", "4", "--batch_size", "4", "--output_dir", str(out)]
    args += ["--device", "cpu", "--shift", "night:5"]
    assert _script().main(args) == 0
    record = json.loads((out / "guarantee_check.json").read_text())
    under = record["shifts"]["night:5"]
    with np.load(out / "counts.npz") as clean, np.load(out / "counts_night_5.npz") as shifted:
        assert shifted["target"].shape == clean["target"][:4].shape
        assert not np.array_equal(shifted["maximize"], clean["maximize"][:4])
        target = shifted["target"]
    with np.errstate(invalid="ignore", divide="ignore"):
        losses = 1 - target[..., 0] / target[..., 1]
    risk = np.nanmean(losses, 0)
    for rule in ("ltt", "naive"):
        chosen = record[rule]["chosen"]
        assert under[rule]["chosen"] == chosen  # chosen on the same clean calibration sets
        violations = sum(c is not None and risk[c] > ALPHA for c in chosen)
        assert under[rule]["violations"] == violations
        assert under[rule]["violation_rate"] == violations / 3


def test_the_shared_options_are_evaluate_py_s(capsys) -> None:
    from costseg.cli import evaluate_parser

    script = _script()
    ours = {a.dest: a for a in script.build_parser()._actions}
    theirs = {a.dest: a for a in evaluate_parser()._actions}
    shared = set(ours) & set(theirs) - {"help"}
    assert len(shared) == 17, shared
    for name in shared:
        for key in ("option_strings", "type", "nargs", "choices", "metavar"):
            assert getattr(ours[name], key) == getattr(theirs[name], key), (name, key)
    own = {"output_dir", "batch_size", "sweep", "target", "maximize", "guarantee"}
    assert {n for n in shared if ours[n].default != theirs[n].default} == own
    for bad, message in ((["--sweep", "0.3"], "--sweep"), (["--device", "tpu"], "device 'tpu'")):
        try:
            code = script.main(bad)
        except SystemExit as stop:  # a parser error
            code = stop.code
        lines = capsys.readouterr().err.strip().splitlines()
        assert code == 2 and len(lines) == 1 and message in lines[0], lines
