"""Every option that an error message of costseg names exists in the command that shows it.

The messages are read from the source (every ``raise``, ``print``, ``fail`` and ``warn`` whose
text holds ``--something``); each option is looked up among the options the command really
parses: evaluate.py's and predict.py's parsers, scripts/check_guarantee.py's, and train.py's
LightningCLI configuration as ``--print_config`` writes it.
"""

from __future__ import annotations

import ast
import contextlib
import importlib.util
import io
import re
from collections.abc import Iterator
from functools import cache
from pathlib import Path

import pytest
import yaml

from costseg.cli import evaluate_parser, predict_parser, train_main

ROOT = Path(__file__).resolve().parents[1]
SCRIPTS = {"check_guarantee.py": "build_parser", "export.py": "parser"}  # script: its parser
SOURCES = [
    *sorted((ROOT / "src" / "costseg").rglob("*.py")),
    *(ROOT / "scripts" / name for name in SCRIPTS),
]
OPTION = re.compile(r"(?<![\w-])--[a-z][a-z0-9_.-]*[a-z0-9_]")
COMMAND = re.compile(r"\b(evaluate|predict|train|check_guarantee|export)\.py\b")
CLAUSE = re.compile(r"[;,()]|: |\. ")
SHOWN_BY = ("print", "fail", "warn", "warning", "error")

# The commands that run each part of costseg (the first match of a path's start); a message
# there names their options, or names the command it means ("evaluate.py --meta").
COMMANDS = {
    "src/costseg/prediction/": {"predict.py"},
    "src/costseg/evaluation/": {"evaluate.py"},
    "src/costseg/meta/": {"evaluate.py"},
    "src/costseg/metrics/": {"evaluate.py"},
    "src/costseg/calibration/": {"evaluate.py", "check_guarantee.py"},
    "src/costseg/data/shift.py": {"evaluate.py", "check_guarantee.py"},
    "src/costseg/training/": {"train.py"},
    "src/costseg/models/adapter.py": {"train.py"},
    "src/costseg/export/": {"export.py"},
    "scripts/export.py": {"export.py"},
    "src/costseg/cli.py": {"train.py"},  # the messages of train.py's --help and --config
    "scripts/check_guarantee.py": {"check_guarantee.py"},
    "src/costseg/checkpoints.py": {"evaluate.py", "predict.py", "train.py", "check_guarantee.py"},
    "src/costseg/report/": {"evaluate.py", "predict.py"},
    "": {"evaluate.py", "predict.py", "check_guarantee.py"},  # networks, rules, report, ...
}


def _text(node: ast.AST) -> str:
    """The text of a message expression, ``{}`` for each value put into it."""
    if isinstance(node, ast.Constant):
        return node.value if isinstance(node.value, str) else ""
    if isinstance(node, ast.JoinedStr):
        return "".join(_text(v) if isinstance(v, ast.Constant) else "{}" for v in node.values)
    return " ".join(t for child in ast.iter_child_nodes(node) if (t := _text(child)))


def _shown(node: ast.AST) -> ast.AST | None:
    """The message of a ``raise`` or of a call that shows one, else None."""
    if isinstance(node, ast.Raise) and node.exc is not None:
        return node.exc
    if isinstance(node, ast.Call):
        name = getattr(node.func, "id", getattr(node.func, "attr", None))
        return node if name in SHOWN_BY else None
    return None


def messages() -> Iterator[tuple[str, str]]:
    """(``path:line``, text) of every message that names an option."""
    for path in SOURCES:
        for node in ast.walk(ast.parse(path.read_text())):
            if (message := _shown(node)) is not None and OPTION.search(text := _text(message)):
                yield f"{path.relative_to(ROOT)}:{node.lineno}", text


def _commands_of(where: str) -> set[str]:
    return next(c for start, c in COMMANDS.items() if where.startswith(start))


@cache
def options(command: str) -> frozenset[str]:
    """Every option ``command`` parses."""
    if command == "train.py":
        return frozenset(_train_options())
    if command in SCRIPTS:
        spec = importlib.util.spec_from_file_location(command, ROOT / "scripts" / command)
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
        parser = getattr(module, SCRIPTS[command])()
    else:
        parser = evaluate_parser() if command == "evaluate.py" else predict_parser()
    return frozenset(parser._option_string_actions)


ADAPTED = ["--model.net", "costseg.models.adapter.NetworkAdapter", "--model.net.init_args.builder",
           "torchvision.models.segmentation.lraspp_mobilenet_v3_large"]  # fmt: skip


def _train_options() -> Iterator[str]:
    """train.py's own flags and every key of the Cityscapes config LightningCLI parses, with
    costseg's network and with the adapter of another library's (docs/usage.md)."""
    yield from ("--config", "--print_config", "--help_all", "--help")
    for network in ([], ADAPTED):
        yield from _config_keys(["--config", "cityscapes", *network, "--print_config"])


def _config_keys(args: list[str]) -> Iterator[str]:
    out = io.StringIO()
    with contextlib.redirect_stdout(out), pytest.raises(SystemExit):
        train_main(args)
    stack = [("--", yaml.safe_load(out.getvalue()))]
    while stack:
        prefix, config = stack.pop()
        for key, value in config.items():
            yield f"{prefix}{key}"
            if isinstance(value, dict):
                stack.append((f"{prefix}{key}.", value))


def owners(where: str, text: str) -> Iterator[tuple[str, set[str]]]:
    """Each option of a message and the commands that must parse it: the command named before
    it in its clause, else those of the message's file that parse the option the message is
    about (the one it starts with: the user gave it)."""
    commands = _commands_of(where)
    if (subject := OPTION.match(text)) is not None:
        commands = {c for c in commands if subject.group() in options(c)} or commands
    for found in OPTION.finditer(text):
        clause = CLAUSE.split(text[: found.start()])[-1]
        named = COMMAND.findall(clause)
        yield found.group(), {f"{named[-1]}.py"} if named else commands


def test_the_walk_finds_the_messages_it_must():
    found = dict(messages())
    texts = [t for w, t in found.items() if w.startswith("src/costseg/report/outputs.py")]
    assert any("pass --overwrite" in t for t in texts), texts
    assert len(found) > 50  # every module's messages, not a few


def test_the_owner_of_an_option_is_the_command_the_message_names():
    where = "src/costseg/prediction/job.py:1"
    text = "--meta_models {} holds no models; evaluate.py --meta with these --cost rules fits them"
    assert list(owners(where, text)) == [
        ("--meta_models", {"predict.py"}),
        ("--meta", {"evaluate.py"}),
        ("--cost", {"evaluate.py"}),
    ]


@pytest.mark.parametrize("where,text", list(messages()))
def test_every_option_a_message_names_parses(where, text):
    for option, commands in owners(where, text):
        missing = [c for c in sorted(commands) if option not in options(c)]
        assert not missing, f"{where}: {option} is no option of {', '.join(missing)}: {text}"
