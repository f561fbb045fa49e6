"""`evaluate.py --defer_sweep` end to end on the tiny checkpoint: defer_sweep.csv against a
decision by brute force over the saved probabilities, AURC in results.json from the CSV's
curves, `--target` against a search over the CSV rows, `--guarantee` along each rule's path, and
the refusals."""

from __future__ import annotations

import csv
import json
import math

import numpy as np
import pytest
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator
from test_cli_errors import _one_line

from costseg.checkpoints import find_checkpoint
from costseg.classes import CLASS_NAMES, ROI_NAMES
from costseg.cli import evaluate_main
from costseg.costs import load_cost, save_cost, symmetric_cost, with_defer
from costseg.metrics.functional.deferral import risk_coverage_area
from costseg.networks.probs_files import load_probs

SWEEP = ["--defer_sweep", "0", "1.2", "0.4"]  # 0, 0.4, 0.8, 1.2
RULES = ["robotistic", "egoistic"]
FEW = ["--num_examples", "3", "--classes", "person", "--no-progress"]


def _evaluate(ckpt: str, out, *extra: str):
    args = ["--ckpt_path", ckpt, "--cost", *RULES, "--output_dir", str(out), *FEW]
    return evaluate_main([*args, *extra])


@pytest.fixture(scope="module")
def ckpt(tiny_run) -> str:
    return str(find_checkpoint(None, runs_dir=tiny_run[2]))


@pytest.fixture(scope="module")
def swept(ckpt, tmp_path_factory):
    out = tmp_path_factory.mktemp("swept")
    target = ["--target", "person:roi1:handled_recall>=0.9", "--maximize", "all:roi1:coverage"]
    return _evaluate(ckpt, out, *SWEEP, *target, "--save-probs"), out


def _rows(out) -> list[dict]:
    with (out / "defer_sweep.csv").open() as f:
        return list(csv.DictReader(f))


def _number(text: str) -> float:
    return float(text) if text not in ("", "nan") else math.nan


def _close(a: float | None, b: float) -> bool:
    a = math.nan if a is None else a  # JSON writes NaN as null
    return (math.isnan(a) and math.isnan(b)) or math.isclose(a, b, rel_tol=1e-9, abs_tol=1e-12)


def _argmin(cost: np.ndarray, p: np.ndarray) -> np.ndarray:
    """(P,) the option of least expected cost as docs/definitions.md §1 and §14 define it in
    float64: each column of ``cost`` (R, N) shifted by its largest entry, the products with
    ``p`` (N, P) summed over the classes in ascending order, ties to the lowest row (a class
    before deferring)."""
    shifted = cost - cost.max(0)
    risks = np.zeros((len(cost), p.shape[1]))
    for k in range(p.shape[0]):
        risks = risks + shifted[:, k : k + 1] * p[k]
    return risks.argmin(0)


def test_the_csv_equals_a_decision_by_brute_force(swept) -> None:
    results, out = swept
    roi = results.roi.numpy()
    labels = {ex.name: ex.label.numpy() for ex in results.examples}
    assert len(labels) == results.num_images == 3
    probs = {s: load_probs(out / "probs" / f"{s}.npz").double().numpy() for s in labels}
    rows = {(r["matrix"], float(r["defer"]), r["class"], int(r["roi"])): r for r in _rows(out)}
    assert len(rows) == len(RULES) * 4 * 1 * 3  # rules × defer costs × classes × RoIs 0-2
    person = CLASS_NAMES.index("person")
    for rule in RULES:
        for defer in (0.0, 0.4, 0.8, 1.2):
            cost = with_defer(load_cost(rule), defer).numpy()
            gt, pred, where = [], [], []
            for stem, p in probs.items():
                choice = _argmin(cost, p.reshape(len(p), -1))
                pred.append(np.where(choice == len(CLASS_NAMES), -1, choice))
                gt.append(labels[stem].ravel())
                where.append(roi.ravel())
            gt, pred, where = (np.concatenate(a) for a in (gt, pred, where))
            for r in range(3):
                inside = (gt != 255) & ((where == r) if r else True)
                kept = inside & (pred != -1)
                row = rows[rule, defer, "person", r]
                is_p = gt == person
                assert _close(_number(row["coverage"]), (kept & is_p).sum() / (inside & is_p).sum())
                with np.errstate(invalid="ignore"):  # nothing kept: NaN
                    wrong = (kept & is_p & (pred != person)).sum() / (kept & is_p).sum()
                    error = (kept & (pred != gt)).sum() / kept.sum()
                assert _close(_number(row["selective_error"]), wrong)
                assert _close(_number(row["coverage_all_classes"]), kept.sum() / inside.sum())
                assert _close(_number(row["selective_error_all_classes"]), error)
    assert any(_number(r["coverage_all_classes"]) < 1 for r in rows.values())  # some deferral


def test_aurc_in_results_json_comes_from_the_csv_curves(swept) -> None:
    _, out = swept
    areas = json.loads((out / "results.json").read_text())["risk_coverage_area"]
    rows = _rows(out)
    for rule in RULES:
        for r in range(3):
            mine = [x for x in rows if x["matrix"] == rule and int(x["roi"]) == r]
            for key, cov, risk in [
                ("person", "coverage", "selective_error"),
                ("all", "coverage_all_classes", "selective_error_all_classes"),
            ]:
                curve = [(_number(x[cov]), _number(x[risk])) for x in mine]
                want = risk_coverage_area(*zip(*curve, strict=True))
                assert _close(areas[rule][key][f"roi{r}"], want), (rule, key, r)
    table = (out / "table.md").read_text()
    assert "AURC" in table and f"RoI 1 ({ROI_NAMES[1]})" in table
    assert (out / "figures" / "risk_coverage_person.png").stat().st_size > 1000
    events = EventAccumulator(str(out), size_guidance={"scalars": 0})
    events.Reload()
    assert "defer_sweep/robotistic/coverage_roi1" in events.Tags()["scalars"]


def test_target_equals_a_search_over_the_csv_rows(swept) -> None:
    _, out = swept
    rows = _rows(out)
    best = json.loads((out / "best.json").read_text())
    person = [r for r in rows if r["class"] == "person" and r["roi"] == "1"]
    meeting = [r for r in person if _number(r["handled_recall"]) >= 0.9]
    top = max(_number(r["coverage_all_classes"]) for r in meeting)
    ties = [r for r in meeting if _number(r["coverage_all_classes"]) == top]
    ties.sort(key=lambda r: -float(r["defer"]))  # ties to the larger defer cost
    want = [{"matrix": r["matrix"], "defer": float(r["defer"])} for r in ties]
    assert best["found"] and best["points"] == want and _close(best["value"], top)


def test_guarantee_walks_each_rule_from_its_smallest_defer_cost(ckpt, tmp_path, capsys) -> None:
    out = tmp_path / "certified"
    guarantee = ["--guarantee", "0.5", "--guarantee_method", "fixed_sequence"]
    target = ["--target", "person:roi0:handled_recall>=0.5", "--maximize", "all:roi0:coverage"]
    split = ["--calibration_split", "train", "--limit", "3"]
    _evaluate(ckpt, out, *SWEEP, *target, *guarantee, *split, "--num_examples", "0")
    record = json.loads((out / "guarantee.json").read_text())
    assert record["method"] == "fixed_sequence" and record["candidates"] == 8
    certified = record["certified"]
    for rule in RULES:  # each path is certified from its smallest defer cost up, without gaps
        costs = [c["defer"] for c in certified if c["matrix"] == rule]
        assert costs == [0.0, 0.4, 0.8, 1.2][: len(costs)]
    assert record["found"] and record["chosen"] in certified
    assert "certified for" in capsys.readouterr().out


def test_refusals_give_one_line(ckpt, tmp_path, capsys) -> None:
    run = ["--ckpt_path", ckpt, "--no-progress", "--output_dir", str(tmp_path / "out")]
    for bad, needle in [
        (["0.5", "0.5", "0.1"], "START < STOP"),
        (["0", "1", "0"], "STEP > 0"),
        (["0", "1", "2"], "one defer cost"),
        (["-1", "1", "0.5"], "defer cost >= 0"),
        (["0", "x", "0.5"], "defer cost >= 0"),
    ]:
        _one_line(evaluate_main, [*run, "--defer_sweep", *bad], capsys, needle)
    chow = tmp_path / "chow.yaml"
    save_cost(chow, with_defer(symmetric_cost(19), 0.5), "chow")
    _one_line(evaluate_main, [*run, "--cost", str(chow), *SWEEP], capsys, "defer row of its own")
    both = [*SWEEP, "--sweep", "0.5", "--target", "person:roi1:recall>=0.9"]
    _one_line(evaluate_main, [*run, *both, "--maximize", "all:roi1:coverage"], capsys, "one sweep")
    bad_all = ["--target", "all:roi1:recall>=0.9", "--maximize", "all:roi1:coverage"]
    _one_line(evaluate_main, [*run, *SWEEP, *bad_all], capsys, "only coverage")
    assert not (tmp_path / "out").exists()  # refused before any output
