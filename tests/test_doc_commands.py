"""Every command the README and docs show is one its program takes as written: each option exists
and accepts the value shown, and evaluate.py's commands pass every option check. Paths in them
(FILE.pth, /data/cityscapes, a.ckpt) stand for the reader's own files; a Cityscapes root is
replaced by a small tree with a train split. ``scripts/run_doc_commands.py`` runs the README's
commands for real on a trained model."""

from __future__ import annotations

import argparse
import importlib.util
import runpy
import shlex
import sys
from pathlib import Path

import pytest
import torch

from costseg.cli import evaluate_parser, predict_parser, train_main
from costseg.data.priors import save_priors
from costseg.evaluation.plan import checked_groups
from costseg.options import EvalOptions

ROOT = Path(__file__).resolve().parents[1]
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
PLACEHOLDERS = ("[--config", "toy]", "[--KEY", "VALUE", "...]")  # README's synopsis of train.py


def _script(name: str):
    spec = importlib.util.spec_from_file_location(name, ROOT / "scripts" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module  # where its options dataclass resolves its annotations
    spec.loader.exec_module(module)
    return module


documented_commands = _script("run_doc_commands").documented_commands


COMMANDS = [
    pytest.param(shlex.split(command)[1:], id=f"{page.name}: {command[:70]}")
    for page in PAGES
    for command in documented_commands(page.read_text())
]


def _program(args: list[str]) -> str:
    return Path(args[0]).name


@pytest.mark.parametrize("args", [c for c in COMMANDS if _program(c.values[0]) == "evaluate.py"])
def test_documented_evaluate_commands_pass_every_option_check(
    args, cityscapes_root, tmp_path, monkeypatch
):
    monkeypatch.chdir(tmp_path)  # the reader's own cost and priors files
    (tmp_path / "my_costs.yaml").write_text("off_diagonal: 1.0\n")
    (tmp_path / "configs").symlink_to(ROOT / "configs")  # the repository's cost files
    save_priors(tmp_path / "priors.pt", torch.full((19, 8, 16), 1 / 19))  # the reader's priors
    if "--probs" in args:  # the reader's saved probabilities (with --data_root: any folder)
        (tmp_path / args[args.index("--probs") + 1]).mkdir(parents=True)
    args = [str(cityscapes_root) if previous == "--data_root" else a
            for previous, a in zip(["", *args[:-1]], args, strict=True)]  # fmt: skip
    opts = EvalOptions(**vars(evaluate_parser().parse_args(args[1:])))
    checked_groups(opts)


@pytest.mark.parametrize("args", [c for c in COMMANDS if _program(c.values[0]) == "predict.py"])
def test_documented_predict_commands_parse(args):
    predict_parser().parse_args(args[1:])


@pytest.mark.parametrize("args", [c for c in COMMANDS if _program(c.values[0]) == "train.py"])
def test_documented_train_commands_parse(args, capsys):
    with pytest.raises(SystemExit) as exit_info:
        train_main([a for a in args[1:] if a not in PLACEHOLDERS] + ["--print_config"])
    assert exit_info.value.code == 0, capsys.readouterr().err


class _Parsed(Exception):
    """Raised in place of a script's work once its arguments are parsed."""


@pytest.mark.parametrize("args", [c for c in COMMANDS if c.values[0][0].startswith("scripts/")])
def test_documented_script_commands_parse(args, monkeypatch):
    parse = argparse.ArgumentParser.parse_args

    def parse_only(self, argv=None, namespace=None):
        raise _Parsed(parse(self, argv, namespace))

    monkeypatch.setattr(argparse.ArgumentParser, "parse_args", parse_only)
    monkeypatch.setattr(sys, "argv", args)
    monkeypatch.syspath_prepend(str(ROOT / "scripts"))
    with pytest.raises(_Parsed):
        runpy.run_path(str(ROOT / args[0]), run_name="__main__")


def test_the_pages_show_commands_of_every_kind():
    programs = {_program(c.values[0]) for c in COMMANDS}
    assert {"evaluate.py", "predict.py", "train.py", "check_guarantee.py"} <= programs
