"""docs/usage.md cannot drift: its tables of training defaults are the YAML files' values, every
option its tables (and predict.md's) name is an option of the parser it documents, and its
tables of an evaluation's files and CSV columns name every file and column of real runs."""

from __future__ import annotations

import csv
import re
from pathlib import Path

import pytest
import yaml

ROOT = Path(__file__).resolve().parents[1]
USAGE = (ROOT / "docs" / "usage.md").read_text()
CONFIGS = {
    name: yaml.safe_load((ROOT / "configs" / f"{name}.yaml").read_text())
    for name in ("toy", "toy_long", "cityscapes")
}
ABSENT = "—"


def section(text: str, heading: str) -> str:
    """The text under a markdown heading, up to the next heading of any level."""
    start = text.index(heading + "\n") + len(heading)
    end = re.search(r"\n#{1,6} ", text[start:])
    return text[start : start + end.start()] if end else text[start:]


def rows(text: str) -> dict[str, list[str]]:
    """``key`` → the cells after it, of each table row whose first cell is a code span."""
    found = {}
    for line in text.splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if line.startswith("| `") and len(cells) > 1:
            found[cells[0].strip("`")] = cells[1:]
    return found


def value(cell: str):
    """A documented value as YAML reads it (backticks dropped; — for a key a config leaves out)."""
    return ABSENT if cell == ABSENT else yaml.safe_load(cell.replace("`", ""))


def _callback_steps(config: dict) -> int:
    callbacks = config["trainer"]["callbacks"]
    return next(c["init_args"]["every_n_train_steps"] for c in callbacks
                if "every_n_train_steps" in c.get("init_args", {}))  # fmt: skip


@pytest.mark.parametrize(
    "heading, keys",
    [
        ("### Model (`--model.*`)", ()),
        ("### Network (`--model.net.init_args.*`)", ("net", "init_args")),
    ],
)
def test_the_model_tables_give_each_config_s_values(heading, keys):
    table = rows(section(USAGE, heading))
    assert len(table) >= 4
    for key, cells in table.items():
        if key in ("net", "loss"):  # entries (class_path / init_args), in their own sections
            continue
        documented = [value(c) for c in cells[0].split(" / ")]
        documented = documented * 3 if len(documented) == 1 else documented
        for name, doc in zip(CONFIGS, documented, strict=True):
            entry = CONFIGS[name]["model"]
            for k in keys:
                entry = entry[k]
            actual = entry.get(key, ABSENT)
            if actual != ABSENT or doc != ABSENT:  # a key left out has the code's default
                assert doc == actual or actual == ABSENT, (key, name, doc, actual)


@pytest.mark.parametrize("name, column", [("toy", 0), ("cityscapes", 1)])
def test_the_data_table_gives_each_config_s_values(name, column):
    table = rows(section(USAGE, "### Data (`--data.init_args.*`)"))
    data = CONFIGS[name]["data"]["init_args"]
    for key, cells in table.items():
        if cells[column] == ABSENT:
            assert not any(k in data for k in key.split(", ")), (name, key)
            continue
        if "," in key:  # train_length, val_length, test_length: one cell of three values
            documented = dict(zip(key.split(", "), cells[column].split(", "), strict=True))
        else:
            documented = {key: cells[column].split(" (")[0]}  # "2 (toy_long: 1)": toy's
        for k, cell in documented.items():
            if k in data:
                assert value(cell) == data[k], (name, k, cell, data[k])
    for k, cell in re.findall(r"^\| `(\w+)` \| [^|]*\(toy_long: ([^)]*)\)", USAGE, flags=re.M):
        assert value(cell) == CONFIGS["toy_long"]["data"]["init_args"][k], k


def test_the_schedule_table_gives_each_config_s_values():
    table = rows(section(USAGE, "### Trainer (`--trainer.*`)"))
    for key in ("max_steps", "val_check_interval", "every_n_train_steps"):
        documented = [value(c) for c in table[key][0].split(" / ")]
        for config, doc in zip(CONFIGS.values(), documented, strict=True):
            actual = config["trainer"].get(key) or _callback_steps(config)
            assert doc == actual, (key, doc, actual)


def _options(parser) -> set[str]:
    return {o for action in parser._actions for o in action.option_strings}


def test_every_option_the_docs_name_is_a_parser_s_option():
    from costseg.cli import evaluate_parser, predict_parser

    documented = {
        "evaluate.py": (section(USAGE, "## evaluate.py") + USAGE.split("## evaluate.py")[1]),
        "predict.md": (ROOT / "docs" / "predict.md").read_text(),
    }
    parsers = {"evaluate.py": evaluate_parser(), "predict.md": predict_parser()}
    for doc, text in documented.items():
        text = text.split("\n## Cost matrices")[0]
        named = {m for m in re.findall(r"^\| `(--[\w-]+)", text, flags=re.M)}
        assert named, doc
        unknown = named - _options(parsers[doc])
        assert not unknown, (doc, sorted(unknown))


def patterns(text: str) -> list[re.Pattern]:
    """The code spans in the first cells of a table's rows as patterns: ``<name>`` and ``*``
    stand for any characters but ``/``, a trailing ``/`` for any path below."""
    found = []
    for line in text.splitlines():
        if line.startswith("| "):
            for span in re.findall(r"`([^`]+)`", line.strip("|").split("|")[0]):
                regex = re.sub(r"<[^>]+>", "[^/]+", re.escape(span)).replace(r"\*", "[^/]*")
                found.append(re.compile(regex + (".*" if span.endswith("/") else "")))
    return found


def test_usage_names_every_file_and_csv_column_of_real_runs(every_output):
    files = patterns(section(USAGE, "### What an evaluation writes"))
    columns = patterns(section(USAGE, "#### Columns of the CSV files"))
    checked = set()
    for folder in every_output:
        for path in sorted(p for p in folder.rglob("*") if p.is_file()):
            name = path.relative_to(folder).as_posix()
            assert any(p.fullmatch(name) for p in files), f"{name} is not in usage.md"
            if path.suffix == ".csv":
                with path.open() as f:
                    header = next(csv.reader(f))
                unnamed = [c for c in header if not any(p.fullmatch(c) for p in columns)]
                assert not unnamed, f"columns of {name} not in usage.md: {unnamed}"
                checked.add(path.name)
    assert {"results.csv", "calibration.csv", "defer_sweep.csv", "fusion.csv"} <= checked
