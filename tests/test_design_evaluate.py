"""``evaluate.py --design``: a matrix designed from several requirements on the held-out images,
certified by Pareto Testing (docs/definitions.md §20); its cost file reproduces the rows the design
reported, and the Python API gives the command line's design."""

import csv
import json
from pathlib import Path

import pytest
import torch
from conftest import write_cityscapes_item

import costseg
from costseg.checkpoints import find_checkpoint
from costseg.cli import evaluate_main, predict_main
from costseg.costs import load_cost
from costseg.data.cityscapes import CityscapesSegmentation
from costseg.networks import load_network

REQUIREMENTS = ["person:roi0:recall>=0.05", "road:roi0:precision>=0.05"]
ARGS = ["--no-progress", "--num_examples", "1", "--cost", "robotistic", "--design_budget", "20",
        "--design_delta", "0.5", "--require", *REQUIREMENTS]  # fmt: skip


@pytest.fixture(scope="module")
def ckpt(tiny_run) -> str:
    return str(find_checkpoint(None, runs_dir=tiny_run[2]))


def _rows(path: Path, rule: str, classes=("person", "building")) -> list[dict]:
    """The rows of ``rule`` in RoIs 0-2 (those a sweep's file holds) for ``classes``, without
    its name."""
    with path.open() as f:
        return [{k: v for k, v in r.items() if k != "matrix"} for r in csv.DictReader(f)
                if r["matrix"] == rule and r["roi"] in "012" and r["class"] in classes]  # fmt: skip


@pytest.mark.figures
def test_the_designed_cost_file_reproduces_the_rows_of_the_design(ckpt, tmp_path):
    out = tmp_path / "design"
    evaluate_main([*ARGS, "--ckpt_path", ckpt, "--output_dir", str(out), "--design",
                   "lagrangian", "--calibration_split", "train"])  # fmt: skip
    record = json.loads((out / "design.json").read_text())
    own = record["searches"][0]
    split = record["split"]
    d1, d2 = split["search (D1)"]["positions"], split["certification (D2)"]["positions"]
    assert split["seed"] == 0 and sorted(d1 + d2) == list(range(8)) and len(d1) == 4
    assert split["held_out"] == "--calibration_split train"
    # a grid of 4 values per multiplier would be coarse: the multipliers are searched by Optuna
    assert own["space"] == "lagrangian" and own["candidates"] == 20
    assert own["search"].startswith("Optuna's TPE sampler")
    assert set(own["images_with_a_defined_loss"][REQUIREMENTS[0]]) == {"search", "certification"}
    assert own["certified"] >= 1 and "chosen" in own
    assert all(own["chosen"]["certification_pvalues"][t] <= 0.5 for t in REQUIREMENTS)
    yaml_file = out / "designed_cost.yaml"
    lines = yaml_file.read_text().split("name:")[0].splitlines()
    header = " ".join(line.removeprefix("#").strip() for line in lines)  # unwrapped
    assert "δ = 0.5" in header and "4 search, 4 certification" in header
    assert "sha256" in header and "--calibration_split train" in header
    matrix = load_cost(yaml_file)
    mu = own["chosen"]["parameters"]
    expected = load_cost("robotistic")
    off = (torch.arange(19) != 11).double(), (torch.arange(19) != 0).double()
    expected[:, 11] += mu["mu_1"] * off[0]  # person recall: its column
    expected[0, :] += mu["mu_2"] * off[1]  # road precision: its row
    torch.testing.assert_close(matrix, expected, rtol=0, atol=0)
    again = tmp_path / "again"
    evaluate_main(["--no-progress", "--num_examples", "1", "--ckpt_path", ckpt, "--output_dir",
                   str(again), "--cost", str(yaml_file)])  # fmt: skip
    assert _rows(again / "results.csv", "designed") == _rows(out / "designed.csv", "designed")
    images = out / "figures"
    assert {"design_matrices.png", "design_front_lagrangian.png"} <= {
        p.name for p in images.iterdir()
    }
    predicted = predict_main(["--ckpt_path", ckpt, "--cost", str(yaml_file), "--input",
                              str(images / "masks_0.png"), "--output_dir", str(tmp_path / "p"),
                              "--no-progress"])  # fmt: skip
    assert any(predicted.rglob("*.png"))


def test_nothing_certified_is_a_result_that_says_why(ckpt, tmp_path):
    out = tmp_path / "none"
    evaluate_main(["--no-progress", "--num_examples", "0", "--ckpt_path", ckpt, "--output_dir",
                   str(out), "--design", "triangle", "--design_budget", "6", "--design_delta",
                   "0.5", "--calibration_split", "train", "--require", "person:roi0:recall>=0.5",
                   "road:roi0:precision>=0.5"])  # fmt: skip
    record = json.loads((out / "design.json").read_text())
    assert len(record["searches"]) == 1  # the triangle is its own comparison
    found = record["searches"][0]
    assert found["certified"] == 0 and not (out / "designed_cost.yaml").exists()
    assert found["nothing_certified"]["failed_constraint"] in record["constraints"]
    assert "Designed value system" in (out / "table.md").read_text()


def test_the_python_api_designs_what_the_command_line_designs(ckpt, tmp_path):
    root = tmp_path / "cs"
    for item in range(8):
        write_cityscapes_item(root, "val", f"frankfurt_000000_{item:06d}", item, (32, 64))
    common = {"roi": "geometric", "design": "aggregate", "design_budget": 12, "seed": 3}
    cli, api = tmp_path / "cli", tmp_path / "api"
    evaluate_main([*ARGS, "--network", f"costseg:{ckpt}", "--data_root", str(root),
                   "--roi", "geometric", "--design", "aggregate", "--design_budget", "12",
                   "--seed", "3", "--output_dir", str(cli)])  # fmt: skip
    results = costseg.evaluate(
        load_network(f"costseg:{ckpt}"), CityscapesSegmentation(root, "val"), ["robotistic"],
        require=REQUIREMENTS, design_delta=0.5, num_examples=1, progress=False, output_dir=str(api),
        **common,
    )  # fmt: skip
    first, second = (json.loads((d / "design.json").read_text()) for d in (cli, api))
    sources = first["certified_for"].pop("source"), second["certified_for"].pop("source")
    assert "sha256" in sources[0] and sources[1] == "python:DeepLabV3Plus"  # a network object
    assert first == second
    assert results.design.split.d1 == first["split"]["search (D1)"]["positions"]
    assert (cli / "design_candidates.csv").read_text() == (
        api / "design_candidates.csv"
    ).read_text()


REGIONAL = ["person:roi0:recall>=0.05", "road:roi1:precision>=0.05", "car:roi3:recall>=0.01"]


def test_a_regional_design_writes_a_regional_file_that_every_command_takes(ckpt, tmp_path):
    """``--design regional`` (docs/definitions.md §21): each requirement moves its own RoI's
    matrix, the file holds the moved RoIs, ``--cost`` reproduces the design's rows under the
    file's name; every requirement's class and RoI are in designed.csv, table.md and the
    console (of ``--cost`` too: the RoIs its certificate names), and the designed rules in
    table.md's main and mIoU tables."""
    import contextlib
    import io

    from costseg.report.certified import certified_requirements

    out = tmp_path / "regional"
    with contextlib.redirect_stdout(io.StringIO()) as printed:
        evaluate_main(["--no-progress", "--num_examples", "1", "--classes", "person", "--ckpt_path",
                       ckpt, "--output_dir", str(out), "--design", "regional", "--design_budget",
                       "20", "--design_delta", "0.5", "--calibration_split", "train", "--require",
                       *REGIONAL])  # fmt: skip
    record = json.loads((out / "design.json").read_text())
    spaces = [s["space"] for s in record["searches"]]
    assert spaces == ["regional", "lagrangian", "triangle"]
    own = record["searches"][0]
    assert "chosen" in own and 0 <= own["changed_share"] <= 1
    mu = own["chosen"]["parameters"]
    stack = load_cost(out / "designed_cost.yaml")
    base, off = load_cost("robotistic"), 1 - torch.eye(19, dtype=torch.float64)
    for r in range(5):  # person (RoI 0) everywhere, road on the street, car on buildings
        want = base.clone()
        want[:, 11] += mu["mu_1"] * off[:, 11]
        want[0, :] += (mu["mu_2"] if r == 1 else 0.0) * off[0, :]
        want[:, 13] += (mu["mu_3"] if r == 3 else 0.0) * off[:, 13]
        torch.testing.assert_close(stack[r], want, rtol=0, atol=0)
    lines = (out / "designed_cost.yaml").read_text().split("name:")[0].splitlines()
    header = " ".join(line.removeprefix("#").strip() for line in lines)  # unwrapped
    assert "--design regional" in header and "moves RoI 1 (street)" in header
    with (out / "designed.csv").open() as f:
        shown = {(r["class"], r["roi"]) for r in csv.DictReader(f) if r["matrix"] == "designed"}
    assert {("road", "1"), ("car", "3"), ("person", "0")} <= shown
    table = (out / "table.md").read_text().split("## Next to the paper")[0]
    assert "| designed |" in table and "|  |  | designed |" in table and "3 building" in table
    assert "Pixels changed: " in (out / "table.md").read_text()
    console = printed.getvalue()
    assert "design: labelled held-out pixels decided otherwise than argmax: regional" in console
    assert any(line.split()[:3] == ["designed", "car", "3"] for line in console.splitlines())
    assert certified_requirements(out / "designed_cost.yaml") == REGIONAL
    again = tmp_path / "again"
    with contextlib.redirect_stdout(io.StringIO()) as printed:
        evaluate_main(["--no-progress", "--num_examples", "1", "--classes", "person", "road",
                       "car", "--ckpt_path", ckpt, "--output_dir", str(again), "--cost",
                       str(out / "designed_cost.yaml")])  # fmt: skip
    lines = printed.getvalue().splitlines()  # RoI 3: the one the file's certificate names
    assert any(line.split()[:3] == ["designed", "car", "3"] for line in lines)
    classes, kept = (
        ("person", "road", "car"),
        ("class", "roi", "precision", "recall", "fn_segments"),
    )
    rows = [[{k: r[k] for k in kept} for r in _rows(path, "designed", classes)]
            for path in (again / "results.csv", out / "designed.csv")]  # fmt: skip
    assert rows[0] == rows[1]  # instances: measured for the classes of --classes only
