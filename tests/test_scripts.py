"""Every script a user runs takes its options the way evaluate.py does: a dataclass of
``option`` fields parsed by ``costseg.cli.build_parser``, so ``--help`` lists them and a mistake
ends in one line on stderr with exit status 2."""

from __future__ import annotations

import ast
import importlib.util
import sys
from functools import cache
from pathlib import Path
from types import ModuleType

import pytest

ROOT = Path(__file__).resolve().parents[1]
SCRIPTS = sorted(p.name for p in (ROOT / "scripts").glob("*.py"))


@cache
def _script(name: str) -> ModuleType:
    """The script as a module (registered, so that its dataclass's annotations resolve)."""
    spec = importlib.util.spec_from_file_location(
        f"scripts_{Path(name).stem}", ROOT / "scripts" / name
    )
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    sys.path.insert(0, str(ROOT / "scripts"))  # the benches import each other
    try:
        spec.loader.exec_module(module)
    finally:
        sys.path.remove(str(ROOT / "scripts"))
    return module


def test_the_scripts_build_no_parser_of_their_own():
    for name in SCRIPTS:
        tree = ast.parse((ROOT / "scripts" / name).read_text())
        called = [getattr(n.func, "attr", getattr(n.func, "id", "")) for n in ast.walk(tree)
                  if isinstance(n, ast.Call)]  # fmt: skip
        assert not {"ArgumentParser", "add_argument"} & set(called), name


@pytest.mark.parametrize("name", SCRIPTS)
def test_each_script_helps_and_refuses_a_mistake_in_one_line(name, capsys):
    main = _script(name).main
    with pytest.raises(SystemExit) as exit_info:
        main(["--help"])
    assert exit_info.value.code == 0 and capsys.readouterr().out.startswith(f"usage: {name}")
    with pytest.raises(SystemExit) as exit_info:
        main(["--no_such_option", "1"])
    err = capsys.readouterr().err.strip().splitlines()
    assert exit_info.value.code == 2 and len(err) == 1, err
    assert err[0].startswith(f"error: {name}: "), err  # the option, or a required one missing


@pytest.mark.parametrize(
    ("name", "args", "flag"),
    [
        ("toy_as_cityscapes.py", ["out", "--size", "64", "0"], "--size"),
        ("count_priors.py", ["labels", "--output", "p.pt", "--sigma", "-1"], "--sigma"),
        ("study_conformal.py", ["--ckpt_path", "a.ckpt", "--alpha", "1.5"], "--alpha"),
        ("study_losses.py", ["--max_steps", "0"], "--max_steps"),
        ("bench_decision.py", ["--share", "2"], "--share"),
        ("bench_pipeline.py", ["--sections", "speed"], "--sections"),
    ],
)
def test_a_bad_value_is_refused_by_its_value_type(name, args, flag, capsys):
    with pytest.raises(SystemExit) as exit_info:
        _script(name).main(args)
    err = capsys.readouterr().err.strip().splitlines()
    assert exit_info.value.code == 2 and len(err) == 1 and flag in err[0], err


def test_a_script_parses_into_its_options_dataclass():
    script = _script("toy_as_cityscapes.py")
    opts = script.parse_options(script.TreeOptions, ["out", "--size", "64", "128"])
    assert opts.root == Path("out") and opts.size == [64, 128] and opts.train == 160
