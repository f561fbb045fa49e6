"""The sections of a cost YAML file (docs/definitions.md §2, §14), read into tensors.

:func:`costseg.costs.load_cost` chooses the form (``off_diagonal``, ``aggregates``, ``classes``)
and validates the result; this module reads each form's keys.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import torch
import yaml

if TYPE_CHECKING:
    from importlib.resources.abc import Traversable


def read_yaml(path: Path | Traversable) -> dict:
    if not path.is_file():
        raise FileNotFoundError(f"cost file not found: {path}")
    try:
        spec = yaml.safe_load(path.read_text())
    except yaml.YAMLError as err:
        raise ValueError(f"{path}: not valid YAML ({err.__class__.__name__})") from None
    if not isinstance(spec, dict):
        raise ValueError(f"{path}: expected a YAML mapping, got {type(spec).__name__}")
    return spec


def _as_matrix(values: object, size: int, what: str) -> torch.Tensor:
    try:
        matrix = torch.tensor(values, dtype=torch.float64)
    except (TypeError, ValueError):
        raise ValueError(f"{what}: 'matrix' must be a list of {size} rows of numbers") from None
    if matrix.shape != (size, size):
        raise ValueError(f"{what}: 'matrix' must be {size}x{size}, got {tuple(matrix.shape)}")
    return matrix


def _positions(names: Sequence[str], class_names: Sequence[str], what: str) -> list[int]:
    unknown = [n for n in names if n not in class_names]
    if unknown:
        raise ValueError(
            f"{what}: unknown class {unknown[0]!r}; expected one of: {', '.join(class_names)}"
        )
    return [list(class_names).index(n) for n in names]


def full_matrix(spec: dict, class_names: Sequence[str]) -> torch.Tensor:
    names = list(spec["classes"])
    if sorted(names) != sorted(class_names):
        _positions(names, class_names, "cost file")
        missing = sorted(set(class_names) - set(names))
        raise ValueError(
            f"cost file: 'classes' must list each of the {len(class_names)} classes once"
            + (f"; missing {missing[0]!r}" if missing else "; a class is listed twice")
        )
    matrix = _as_matrix(spec.get("matrix"), len(names), "cost file")
    order = _positions(names, class_names, "cost file")
    cost = torch.empty_like(matrix)
    cost[torch.tensor(order)[:, None], torch.tensor(order)[None, :]] = matrix
    return cost


def _aggregate_table(spec: dict, folder: Path | Traversable) -> tuple[dict, list]:
    """The aggregates' classes by name, and the suppressed classes, of an aggregate cost file."""
    table = spec["aggregates"]
    if isinstance(table, str):
        table = read_yaml(folder / table)
    return dict(table["aggregates"]), list(table.get("suppressed", []))


def expand_aggregates(
    spec: dict, folder: Path | Traversable, class_names: Sequence[str]
) -> torch.Tensor:
    groups, suppressed = _aggregate_table(spec, folder)
    order = list(spec["order"])
    if sorted(order) != sorted(groups):
        raise ValueError(
            f"cost file: 'order' {order} must name each aggregate once: {', '.join(groups)}"
        )
    agg_of = torch.full((len(class_names),), -1, dtype=torch.long)
    for a, name in enumerate(order):
        for i in _positions(groups[name], class_names, f"aggregate {name!r}"):
            if agg_of[i] >= 0:
                raise ValueError(f"class {class_names[i]!r} is in two aggregates")
            agg_of[i] = a
    sup = _positions(suppressed, class_names, "suppressed classes")
    unassigned = [class_names[i] for i in range(len(class_names)) if agg_of[i] < 0 and i not in sup]
    if unassigned:
        raise ValueError(f"class {unassigned[0]!r} is in no aggregate and not suppressed")
    matrix = _as_matrix(spec.get("matrix"), len(order), "aggregate cost file")
    safe = agg_of.clamp(min=0)
    cost = matrix[safe[:, None], safe[None, :]]
    cost[agg_of[:, None] == agg_of[None, :]] = float(spec["epsilon"])
    cost[:, sup] = float(spec["suppressed_column_cost"])  # s: sky as the true class
    cost[sup, :] = float(spec["suppressed_row_cost"])  # M: predicting sky
    return cost.fill_diagonal_(0.0)


def defer_costs(
    spec: dict, folder: Path | Traversable, class_names: Sequence[str]
) -> float | torch.Tensor:
    """A cost file's ``defer``: a number, or (N,) from its mapping (see :func:`load_cost`)."""
    value = spec["defer"]
    if isinstance(value, bool) or not isinstance(value, (int, float, dict)):
        raise ValueError(
            "cost file: 'defer' must be a number or a mapping from class names, aggregate names "
            f"or 'default' to numbers, got {value!r}"
        )
    if not isinstance(value, dict):
        return float(value)
    groups = _aggregate_table(spec, folder)[0] if "aggregates" in spec else {}
    row = torch.full((len(class_names),), math.nan, dtype=torch.float64)
    # the default, then aggregates, then classes: the more specific entry wins
    keys = sorted(value, key=lambda key: (key != "default", key not in groups))
    for key in keys:
        number = value[key]
        if isinstance(number, bool) or not isinstance(number, (int, float)):
            raise ValueError(f"cost file: 'defer' of {key!r} must be a number, got {number!r}")
        if key == "default":
            row[:] = number
        elif key in groups:
            row[_positions(groups[key], class_names, f"aggregate {key!r}")] = float(number)
        else:
            row[_positions([key], class_names, "cost file: 'defer'")] = float(number)
    if row.isnan().any():
        missing = class_names[int(row.isnan().nonzero()[0])]
        raise ValueError(
            f"cost file: 'defer' gives no cost for class {missing!r} (name it, its aggregate, "
            "or 'default')"
        )
    return row
