"""Every bad input of `evaluate.py`, `train.py` and `scripts/check_guarantee.py` ends with one
line on stderr and status 2, which never starts with an exception's class name."""

import importlib.util
import sys
from pathlib import Path

import pytest
import torch
import yaml
from conftest import TINY_TRAIN
from torch._utils import ExceptionWrapper

from costseg.checkpoints import find_checkpoint
from costseg.classes import CLASS_NAMES
from costseg.cli import CLASS_PREFIX, evaluate_main, train_main, user_errors
from costseg.costs import COSTS_DIR

CHECK_GUARANTEE = Path(__file__).resolve().parents[1] / "scripts" / "check_guarantee.py"


def _one_line(main, args, capsys, *needles):
    with pytest.raises(SystemExit) as exit_info:
        main(args)
    assert exit_info.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    assert all(n in err[0] for n in needles), err[0]
    assert err[0].startswith("error: ") and not CLASS_PREFIX.match(err[0][7:]), err[0]


@pytest.fixture(scope="module")
def ckpt(tiny_run):
    return str(find_checkpoint(None, runs_dir=tiny_run[2]))


def _bad_entry(tmp_path):
    matrix = (1 - torch.eye(19)).tolist()
    matrix[11][2] = -5
    path = tmp_path / "bad.yaml"
    path.write_text(yaml.safe_dump({"classes": list(CLASS_NAMES), "matrix": matrix}))
    return str(path)


def _target(text):
    return ["--sweep", "0.5", "--target", text, "--maximize", "person:roi1:precision"]


MONITOR = ["--monitor_require", "person:roi1:recall>=0.8"]
REGIONAL_MONITOR = ["--monitor_require", "car:roi1:recall>=0.8", "--monitor_space", "regional"]
DESIGN = ["--require", "person:roi1:recall>=0.9", "--design_delta", "0.1", "--design", "lagrangian"]
TESTS = Path(__file__).parent  # a folder that holds no record of scored images

EVALUATE_CASES = {
    "unknown cost": (["--cost", "selfish"], ["unknown cost 'selfish'", "ml"]),
    "aggregate table as cost": (
        ["--cost", str(COSTS_DIR / "aggregates.yaml")],
        ["aggregate table"],
    ),
    "zero batch": (["--batch_size", "0"], ["--batch_size", ">= 1"]),
    "zero limit": (["--limit", "0"], ["--limit", ">= 1"]),
    "negative limit": (["--limit", "-3"], ["--limit", ">= 1"]),
    "word as limit": (["--limit", "ten"], ["--limit", "'ten'"]),
    "negative examples": (["--num_examples", "-1"], ["--num_examples", ">= 0"]),
    "zero sweep": (["--sweep", "0"], ["--sweep", "1/n"]),
    "negative sweep": (["--sweep", "-0.1"], ["--sweep"]),
    "sweep not 1/n": (["--sweep", "0.3"], ["--sweep", "1/n"]),
    "zero alpha sweep": (["--alpha_sweep", "0"], ["--alpha_sweep"]),
    "two vertices": (["--sweep", "0.5", "--vertices", "robotistic"], ["--vertices"]),
    "ml vertex": (["--sweep", "0.5", "--vertices", "robotistic", "altruistic", "ml"], ["vertex"]),
    "ml alpha cost": (["--alpha_sweep", "0.5", "--alpha_cost", "ml"], ["--alpha_cost"]),
    "target without sweep": (
        ["--target", "person:roi1:recall>=0.9", "--maximize", "person:roi1:precision"],
        ["--sweep"],
    ),
    "unknown RoI": (_target("person:roi9:recall>=1"), ["unknown RoI 'roi9'"]),
    "unparsable target": (_target("person:roi1:recall about 1"), ["cannot parse"]),
    "recall above 1": (_target("person:roi1:recall>=1.5"), ["recall", "[0, 1]"]),
    "negative fp rate": (_target("person:roi1:fp_rate<=-0.1"), ["fp_rate", "[0, 1]"]),
    "unknown metric": (_target("person:roi1:sharpness>=1"), ["unknown metric 'sharpness'"]),
    "guarantee above 1": (
        [*_target("person:roi1:recall>=0.9"), "--guarantee", "1.5"],
        ["--guarantee", "(0, 1)"],
    ),
    "guarantee without target": (["--sweep", "0.5", "--guarantee", "0.1"], ["needs --target"]),
    "target over two sweeps": (
        [*_target("person:roi1:recall>=0.9"), "--alpha_sweep", "0.5"],
        ["one sweep", "2 (grid, alpha)"],
    ),
    "guarantee without sweep": (
        [
            "--target",
            "person:roi1:recall>=0.9",
            "--maximize",
            "person:roi1:precision",
            "--guarantee",
            "0.1",
        ],
        ["--guarantee chooses among the points of a sweep: --sweep, --defer_sweep, --alpha_sweep"],
    ),
    "too few calibration images": (
        [*_target("person:roi1:recall>=0.9"), "--guarantee", "0.1"],
        ["calibration images cannot certify anything", "at least", "--calibration_split"],
    ),
    "overlapping calibration": (
        ["--calibrate", "temperature", "--calibration_split", "val"],
        ["overlaps"],
    ),
    "unknown calibration": (["--calibrate", "platt"], ["--calibrate", "platt"]),
    "unknown split": (["--split", "holdout"], ["--split", "holdout"]),
    "unknown scaling": (["--vertex_scaling", "max"], ["--vertex_scaling"]),
    "unknown option": (["--costs", "egoistic"], ["unrecognized arguments"]),
    "unknown class": (["--classes", "unicorn"], ["unknown class 'unicorn'"]),
    "missing cuda": (["--device", "cuda"], ["cuda", "not available"]),
    "unknown device": (["--device", "tpu"], ["device 'tpu'"]),
    "probs with a checkpoint": (["--probs", "somewhere"], ["--probs replaces the network"]),
    "probs with a network": (
        ["--probs", "somewhere", "--network", "hf:x"],
        ["--probs replaces the network"],
        False,
    ),
    "checkpoint option without a path": (["--ckpt_path"], ["--ckpt_path", "expected at least one"]),
    "network option without a spec": (["--network"], ["--network", "expected at least one"]),
    "probs folder missing": (["--probs", "somewhere"], ["--probs folder not found"], False),
    "probs without data": (["--probs", str(TESTS)], ["--probs needs --data_root"], False),
    "missing data root": (["--data_root", "no/such/cityscapes"], ["no/such/cityscapes"]),
    "conformal alpha of one": (["--conformal", "1"], ["--conformal", "(0, 1)"]),
    "conformal options without it": (
        ["--conformal_sets", "aps"],
        ["--conformal_sets goes with --conformal"],
    ),
    "conformal tau without binary loss": (
        ["--conformal", "0.1", "--conformal_tau", "0.8"],
        ["--conformal_tau goes with --conformal_loss binary"],
    ),
    "conformal roi out of range": (
        ["--conformal", "0.1", "--conformal_roi", "7"],
        ["--conformal_roi", "invalid choice: 7"],
    ),
    "several targets without a design": (
        [
            *_target("person:roi1:recall>=0.9")[:2],
            "--maximize",
            "person:roi1:precision",
            "--target",
            "person:roi1:recall>=0.9",
            "rider:roi1:recall>=0.9",
        ],
        ["a sweep's point is chosen for one --target", "--require"],
    ),
    "design without requirements": (["--design", "lagrangian"], ["--design needs", "--require"]),
    "design without delta": (
        ["--design", "triangle", "--require", "person:roi1:recall>=0.9"],
        ["--design_delta"],
    ),
    "design with the sweep's flags": (
        ["--design", "triangle", "--target", "person:roi1:recall>=0.9", "--guarantee", "0.1"],
        ["--design needs", "--require", "--design_delta", "choose a point of a sweep"],
    ),
    "design delta of one": ([*DESIGN, "--design_delta", "1"], ["--design_delta", "(0, 1)"]),
    "requirement without design": (
        ["--require", "person:roi1:recall>=0.9"],
        ["--require goes with --design"],
    ),
    "requirement of no risk level": (
        [*DESIGN[:-1], "triangle", "--require", "person:roi1:recall>=1"],
        ["--require person:roi1:recall>=1", "α"],
    ),
    "design space unknown": (["--design", "simplex"], ["--design", "invalid choice"]),
    "design budget of one": (["--design", "triangle", "--design_budget", "1"], [">= 2"]),
    "design share above one": (
        [*DESIGN, "--design_pixels", "1.5"],
        ["--design_pixels", "(0, 1]"],
    ),
    "lagrangian on coverage": (
        [*DESIGN[2:], "--require", "person:roi1:coverage>=0.9"],
        ["coverage"],
    ),
    "aggregate template without aggregates": (
        [*DESIGN[:-1], "aggregate", "--design_base", "robotistic"],
        ["aggregate"],
    ),
    "design objective of segments": (
        [*DESIGN, "--design_maximize", "person:roi1:fp_rate"],
        ["pixel rate"],
    ),
    "minimize without design": (
        ["--design_minimize", "person:roi1:recall"],
        ["--design_minimize goes with"],
    ),
    "design search of the triangle": (
        [*DESIGN[:-1], "triangle", "--design_search", "grid"],
        ["--design_search goes with --design lagrangian"],
    ),
    "design requirement twice": (
        [*DESIGN, "--require", "person:roi1:recall>=0.9", "person:street:recall>=0.9"],
        ["--require gives person:roi1:recall>=0.9 twice"],
    ),
    "design requirement misspelt": (
        [*DESIGN, "--require", "person:roi1:recal>=0.9"],
        ["--require person:roi1:recal>=0.9", "unknown metric"],
    ),
    "design on too few held-out images": (
        [*DESIGN, "--limit", "2"],
        ["1 held-out image(s)", "at least 44 held-out images", "--calibration_split"],
    ),
    "design base of triangle": (
        [*DESIGN[:-1], "triangle", "--design_base", "egoistic"],
        ["--design_base goes with"],
    ),
    "monitor step of zero": ([*MONITOR, "--monitor_eta", "0"], ["--monitor_eta", "> 0"]),
    "monitor option without a monitor": (
        ["--monitor_delay", "2"],
        ["--monitor_delay goes with --monitor_require"],
    ),
    "monitor delay beyond the stream": (
        [*MONITOR, "--monitor_delay", "3", "--limit", "3"],
        ["--monitor_delay 3", "3 reported images", "no label would arrive"],
    ),
    "monitor of a rate no multiplier steers": (
        ["--monitor_require", "person:roi1:dice>=0.5"],
        ["--monitor_require person:roi1:dice>=0.5", "recall or precision"],
    ),
    "monitor requirement twice": (
        [*MONITOR, "person:roi1:recall>=0.9"],
        ["--monitor_require gives the rate of person:roi1:recall>=0.8 twice"],
    ),
    "monitor share above one": ([*MONITOR, "--monitor_labelled", "1.5"], ["--monitor_labelled"]),
    "monitor start missing": (
        [*MONITOR, "--monitor_start", "no/such.yaml"],
        ["--monitor_start: no such file no/such.yaml"],
    ),
    "monitor start outside the space": (
        [*MONITOR, "--monitor_start", str(COSTS_DIR / "altruistic.yaml")],
        ["altruistic.yaml", "is not C₀ + Σ μ_i A_i"],
    ),
    "monitor base of priors": ([*MONITOR, "--monitor_base", "ml"], ["--monitor_base ml", "C₀"]),
    "monitor regional base without the regional space": (
        [*MONITOR, "--monitor_base", str(COSTS_DIR / "street_person.yaml")],
        ["street_person.yaml", "with --monitor_space regional"],
    ),
    "monitor regional start outside the regional space": (
        [*REGIONAL_MONITOR, "--monitor_start", str(COSTS_DIR / "street_person.yaml")],
        ["street_person.yaml", "is not C₀"],
    ),
    "shift onset beyond the stream": (
        ["--shift", "fog:1", "--shift_onset", "3", "--limit", "3"],
        ["--shift_onset 3", "no image would be shifted"],
    ),
    "shift onset without a shift": (["--shift_onset", "3"], ["--shift_onset goes with --shift"]),
}


@pytest.mark.parametrize("case", sorted(EVALUATE_CASES))
def test_evaluate_bad_option(case, ckpt, capsys):
    args, needles, *with_checkpoint = EVALUATE_CASES[case]
    if case == "missing cuda" and torch.cuda.is_available():
        pytest.skip("this machine has CUDA")
    source = ["--ckpt_path", ckpt] if with_checkpoint != [False] else []
    _one_line(evaluate_main, [*source, *args, "--no-progress"], capsys, *needles)


def test_evaluate_bad_files(ckpt, tmp_path, capsys):
    run = ["--no-progress", "--ckpt_path"]
    _one_line(evaluate_main, [*run, ckpt, "--cost", _bad_entry(tmp_path)], capsys, "[11, 2]")
    _one_line(evaluate_main, [*run, str(tmp_path)], capsys, "is a directory")
    text = tmp_path / "notes.ckpt"
    text.write_text("not a checkpoint")
    _one_line(evaluate_main, [*run, str(text)], capsys, "notes.ckpt", "not a readable torch file")
    _one_line(evaluate_main, [*run, str(tmp_path / "none.ckpt")], capsys, "not found")
    afile = tmp_path / "afile"
    afile.write_text("x")
    _one_line(evaluate_main, [*run, ckpt, "--output_dir", str(afile)], capsys, "is a file")
    inside = str(afile / "sub")
    _one_line(evaluate_main, [*run, ckpt, "--output_dir", inside], capsys, "cannot write")


def test_evaluate_bad_ensemble_members(ckpt, tmp_path, capsys):
    run = ["--no-progress", "--ckpt_path", ckpt]
    _one_line(evaluate_main, [*run, str(tmp_path / "none.ckpt")], capsys, "none.ckpt", "not found")
    _one_line(evaluate_main, [*run, "--network", "vainf:none.pth"], capsys, "none.pth", "not found")
    _one_line(evaluate_main, [*run, "--network", "tf:x"], capsys, "tf:x")
    # every member is checked before the first is loaded (which prints "checkpoint: ...")
    with pytest.raises(SystemExit):
        evaluate_main([*run, "--network", "hf:no_such_dir"])
    out, err = capsys.readouterr()
    assert "no_such_dir" in err and "checkpoint:" not in out, out


def test_evaluate_without_any_checkpoint(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    _one_line(evaluate_main, ["--no-progress"], capsys, "no last.ckpt found", "python train.py")


TRAIN_CASES = {
    "negative steps": (["--trainer.max_steps=-5"], ["max_steps"]),
    "zero steps": (["--trainer.max_steps=0"], ["max_steps", ">= 1"]),
    "negative learning rate": (["--model.lr=-1"], ["--model.lr", "> 0"]),
    "gpu config without gpu": (
        ["--config=configs/cityscapes.yaml"],
        ["--trainer.accelerator cpu", "--trainer.precision 32-true"],
    ),
    "zero batch": (["--data.init_args.batch_size=0"], ["batch_size"]),
    "unknown backbone": (["--model.net.init_args.backbone=resnet7"], ["resnet7"]),
    "unknown rule": (["--model.val_costs=[selfish]"], ["unknown cost 'selfish'"]),
    "unknown option": (["--model.colour=blue"], ["colour"]),
    "missing config": (["--config=no/such.yaml"], ["no/such.yaml"]),
    "missing accelerator": (["--trainer.accelerator=tpu"], ["torch_xla"]),
    "missing gpu": (["--trainer.accelerator=gpu"], ["gpu"]),
    "missing checkpoint": (["--ckpt_path=no/such.ckpt"], ["checkpoint not found"]),
    "negative focal gamma": (
        ["--model.loss=FocalLoss", "--model.loss.gamma=-1"],
        ["FocalLoss gamma must be >= 0"],
    ),
    "class weights of the wrong length": (
        ["--model.loss=WeightedCrossEntropy", "--model.loss.weights=[1, 2]"],
        ["19 positive numbers"],
    ),
    "unknown cost of a loss": (
        ["--model.loss=ExpectedCostCrossEntropy", "--model.loss.cost=selfish"],
        ["unknown cost 'selfish'"],
    ),
    "pixel priors on random crops": (
        ["--config=cityscapes", "--config=losses/logit_adjusted", "--trainer.accelerator=cpu"],
        ["random crops", "priors: global"],
    ),
}


@pytest.mark.parametrize("case", sorted(TRAIN_CASES))
def test_train_bad_option(case, tmp_path, capsys):
    args, needles = TRAIN_CASES[case]
    logs = f"--trainer.logger.init_args.save_dir={tmp_path}"
    if "gpu" in case and torch.cuda.is_available():
        pytest.skip("this machine has a GPU")
    # A later option overrides an earlier one; --config must come first to be read first.
    order = [*args, *TINY_TRAIN, logs] if case == "missing config" else [*TINY_TRAIN, logs, *args]
    if case in ("gpu config without gpu", "pixel priors on random crops"):  # Cityscapes' options
        order = [*args, logs]
    _one_line(train_main, order, capsys, *needles)


@pytest.mark.workers
def test_an_error_of_a_data_loader_worker_is_one_line_without_its_class_name(
    ckpt, cityscapes_root, tmp_path, capsys
):
    image = next((cityscapes_root / "leftImg8bit" / "val").rglob("*.png"))
    image.write_text("not an image")  # read in a DataLoader worker: the error has its traceback
    out = str(tmp_path / "out")
    args = ["--ckpt_path", ckpt, "--data_root", str(cityscapes_root), "--cost", "robotistic",
            "--num_examples", "0", "--output_dir", out, "--no-progress"]  # fmt: skip
    with pytest.raises(SystemExit) as exit_info:
        evaluate_main(args)
    errors = [line for line in capsys.readouterr().err.splitlines() if "error" in line.lower()]
    assert exit_info.value.code == 2
    why = f"cannot decode {image}: cannot identify image file '{image}'"
    assert errors == [f"error: {why}; the partial outputs in {out} are marked INCOMPLETE"]


def test_a_reraised_error_keeps_only_its_message(capsys):
    """torch's own wrapper of a worker's error (its traceback, then ``ValueError: ...``)."""
    try:
        raise OSError("disk full")
    except OSError:
        wrapped = ExceptionWrapper(sys.exc_info(), "in DataLoader worker process 0")
    with pytest.raises(SystemExit), user_errors():
        wrapped.reraise()
    assert capsys.readouterr().err == "error: disk full\n"
    with pytest.raises(SystemExit), user_errors():
        raise ValueError("torch.OutOfMemoryError: ValueError: nested")
    assert capsys.readouterr().err == "error: nested\n"
    with pytest.raises(SystemExit), user_errors():
        raise FileNotFoundError
    assert capsys.readouterr().err == "error: failed without a message (FileNotFoundError)\n"


def test_check_guarantee_bad_input(tmp_path, capsys):
    spec = importlib.util.spec_from_file_location("check_guarantee", CHECK_GUARANTEE)
    script = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(script)
    missing = tmp_path / "none.ckpt"
    _one_line(
        script.main,
        ["--ckpt_path", str(missing)],
        capsys,
        f"error: checkpoint not found: {missing}",
    )


NEEDS_THE_DATA = {"too few calibration images": "the calibration split's size"}


@pytest.mark.parametrize("case", sorted(set(EVALUATE_CASES) - set(NEEDS_THE_DATA)))
def test_every_bad_option_is_refused_before_anything_heavy(case, ckpt, capsys, monkeypatch):
    """The option checks run before the figure workers start, a network is opened or a dataset
    is built: each of those fails the test if it is reached."""

    def reached(*_, **__):
        raise AssertionError("reached before the options were checked")

    for name in ("costseg.workers.start", "costseg.evaluation.plan.open_sources",
                 "costseg.evaluation.plan.build_dataset"):  # fmt: skip
        monkeypatch.setattr(name, reached)
    args, needles, *with_checkpoint = EVALUATE_CASES[case]
    if case == "missing cuda" and torch.cuda.is_available():
        pytest.skip("this machine has CUDA")
    source = ["--ckpt_path", ckpt] if with_checkpoint != [False] else []
    _one_line(evaluate_main, [*source, *args, "--no-progress"], capsys, *needles)
