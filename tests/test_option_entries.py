"""Every option reaches the same checks from every entry: each option's bad value is refused by
the Python API (``costseg.evaluate``, ``costseg.predict``) and by the command line, naming the
option, before any heavy work (the network moved, the forkserver, data read)."""

import argparse
import contextlib
import dataclasses
import sys
import typing

import pytest
import torch
from torch import nn

import costseg
from costseg import api, workers
from costseg.cli import evaluate_main, predict_main
from costseg.options import EvalOptions, PredictOptions

REFUSED_TEXTS = ("not_a_choice", "-1", "0", "1.5", "0.3", "x")
"""Texts tried in turn as an option's value: the first one the option's checks refuse is its
bad value."""


def _item_hint(hint):
    kinds = [a for a in typing.get_args(hint) if a is not type(None)]
    hint = kinds[0] if typing.get_origin(hint) in (typing.Union, type(int | None)) else hint
    return typing.get_args(hint)[0] if typing.get_origin(hint) is list else hint


def _bad_text(field, hint) -> str | None:
    """A text the option refuses by its value alone, or None (a free text such as a path)."""
    item = _item_hint(hint)
    if typing.get_origin(item) is typing.Literal:
        return "7" if all(isinstance(c, int) for c in typing.get_args(item)) else "not_a_choice"
    parse = field.metadata.get("type", float if item in (int, float) else None)
    for text in REFUSED_TEXTS if parse else ():
        try:
            parse(text)
        except (ValueError, argparse.ArgumentTypeError):
            return text
    return None


def _python_value(text: str, hint):
    """The bad text as the Python API would be given it: a number where the option takes one,
    in a list where it takes several."""
    item, value = _item_hint(hint), text
    numeric = item in (int, float) or (typing.get_origin(item) is typing.Literal and text == "7")
    if numeric:
        with contextlib.suppress(ValueError):
            value = float(text) if item is float else int(text)
    unwrapped = [a for a in typing.get_args(hint) if a is not type(None)] or [hint]
    return [value] if typing.get_origin(unwrapped[0]) is list else value


def _cases(options: type):
    hints = typing.get_type_hints(options)
    for f in dataclasses.fields(options):
        text = _bad_text(f, hints[f.name])
        if f.init and hints[f.name] is not bool and text is not None:
            yield f, hints[f.name], text


def _cli_args(field, text):
    count = field.metadata.get("nargs")
    return [
        field.metadata.get("flag", f"--{field.name}"),
        *[text] * (count if isinstance(count, int) else 1),
    ]


EVALUATE = list(_cases(EvalOptions))
PREDICT = list(_cases(PredictOptions))


def test_the_walk_covers_the_options_of_a_value():
    names = {f.name for f, _, _ in EVALUATE}
    assert {"conformal", "conformal_loss", "guarantee_method", "roi", "conformal_roi"} <= names
    assert len(EVALUATE) >= 25 and len(PREDICT) >= 10


@pytest.fixture
def nothing_heavy(monkeypatch):
    """Heavy work fails the test: the forkserver, a module's source or a named one, the
    evaluation itself, the prediction's pass over the images."""

    def heavy(*args, **kwargs):
        raise AssertionError("heavy work began before the options were checked")

    monkeypatch.setattr(workers, "start", heavy)
    monkeypatch.setattr(api, "module_source", heavy)
    monkeypatch.setattr("costseg.evaluation.run.evaluate", heavy)
    monkeypatch.setattr("costseg.prediction.job.open_sources", heavy)
    monkeypatch.setattr("costseg.prediction.job.run", heavy)


NETWORK = nn.Conv2d(3, 19, 1)
DATASET = [(torch.zeros(3, 8, 8, dtype=torch.uint8), torch.zeros(8, 8, dtype=torch.int64))]


@pytest.mark.parametrize(("field", "hint", "text"), EVALUATE, ids=[f.name for f, *_ in EVALUATE])
def test_evaluate_refuses_each_bad_value_from_python_and_the_command_line(
    field, hint, text, nothing_heavy, capsys
):
    flag = field.metadata.get("flag", f"--{field.name}")
    with pytest.raises(ValueError, match=flag):
        costseg.evaluate(NETWORK, DATASET, **{field.name: _python_value(text, hint)})
    with pytest.raises(SystemExit) as exit_info:
        evaluate_main(_cli_args(field, text))
    assert exit_info.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: ") and flag in err[0], err


@pytest.mark.parametrize(("field", "hint", "text"), PREDICT, ids=[f.name for f, *_ in PREDICT])
def test_predict_refuses_each_bad_value_from_python_and_the_command_line(
    field, hint, text, nothing_heavy, capsys, tmp_path
):
    flag = field.metadata.get("flag", f"--{field.name}")
    with pytest.raises(ValueError, match=flag):
        costseg.predict(NETWORK, [tmp_path], **{field.name: _python_value(text, hint)})
    with pytest.raises(SystemExit) as exit_info:
        predict_main(["--input", str(tmp_path), *_cli_args(field, text)])
    assert exit_info.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: ") and flag in err[0], err


def test_booleans_and_lists_of_the_wrong_kind_are_refused_from_python(nothing_heavy):
    for name, value, flag in (
        ("save_probs", "yes", "--save-probs"),
        ("classes", "person", "--classes"),
        ("crop", [64], "--crop"),
        ("vertices", ["robotistic", "altruistic"], "--vertices"),
    ):
        with pytest.raises(ValueError, match=flag):
            costseg.evaluate(NETWORK, DATASET, **{name: value})


def test_predict_checks_the_values_once_then_opens_the_module(monkeypatch, tmp_path):
    """The Python API and the command line pass the predict job's one check of every value;
    the module given in Python is opened after it, on the plan's device."""
    from PIL import Image

    from costseg.prediction import job

    Image.new("RGB", (16, 8)).save(tmp_path / "photo.png")
    checked, opened = [], []
    check = job.check_values
    monkeypatch.setattr(job, "check_values", lambda opts: checked.append(check(opts)))
    open_module = api.module_source
    monkeypatch.setattr(
        api, "module_source", lambda *a, **k: opened.append(len(checked)) or open_module(*a, **k)
    )
    monkeypatch.setattr(job, "run", lambda planned: planned.output_dir)
    out = costseg.predict(NETWORK, [tmp_path / "photo.png"], output_dir=str(tmp_path / "out"))
    assert out == tmp_path / "out" and len(checked) == 1 and opened == [1]
    monkeypatch.setattr(job, "open_sources", lambda *a: open_module(NETWORK, a[3]))
    predict_main(["--input", str(tmp_path / "photo.png"), "--output_dir", str(tmp_path / "cli")])
    assert len(checked) == 2  # the command line's run: the same one check


def test_evaluate_checks_every_option_once_on_each_entry(monkeypatch, tmp_path):
    """The command line and the Python API check an evaluation's options once, before the
    forkserver or the network (the plan takes the checked rule groups)."""
    from costseg.evaluation import checks, run

    checked = []
    check = checks.check_values
    monkeypatch.setattr(checks, "check_values", lambda opts: checked.append(check(opts)))
    planned = []
    monkeypatch.setattr(run, "plan", lambda *a: planned.append(len(checked)) or sys.exit(0))
    monkeypatch.setattr(run.workers, "start", lambda preload=(): None)
    with pytest.raises(SystemExit):
        evaluate_main(["--output_dir", str(tmp_path / "cli")])
    with pytest.raises(SystemExit):
        costseg.evaluate(NETWORK, DATASET, output_dir=str(tmp_path / "api"))
    assert planned == [1, 2]
