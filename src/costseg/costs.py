"""Confusion cost matrices: load, validate, build (symmetric, aggregates, sky, regional), mix,
grid; the class weights of a matrix.

A cost matrix ``C`` is (N, N) with **rows = predicted class, columns = true class**
(docs/definitions.md §1), or (N + 1, N) with a last row of defer costs ``c_defer[j] >= 0``, the
cost of deferring a pixel whose true class is j (docs/definitions.md §14). A **regional** value
system (docs/definitions.md §21) is a stack (R + 1, M, N) of such matrices, index 0 the default
(the whole image), index r the matrix of RoI r (classes.py's RoI ids).
Matrices are float64 tensors so that YAML values and mixtures stay exact.

>>> C = load_cost("egoistic")
>>> C.shape, C[11, 2].item(), C[2, 11].item()  # person predicted on a building; and vice versa
(torch.Size([19, 19]), 1000.0, 1.0)
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import torch
import yaml

from costseg import CONFIGS
from costseg.atomic import write_bytes
from costseg.classes import CLASS_NAMES, NUM_ROIS, ROI_IDS, ROI_NAMES
from costseg.values import steps_per_unit

if TYPE_CHECKING:
    from importlib.resources.abc import Traversable

COSTS_DIR = CONFIGS / "costs"
PRESETS = ("robotistic", "altruistic", "egoistic")


def validate_cost(cost: torch.Tensor, class_names: Sequence[str] = CLASS_NAMES) -> torch.Tensor:
    """Check that ``cost`` is a valid confusion cost matrix for ``class_names``.

    Valid (docs/definitions.md §1, §14): shape (N, N) with N = len(class_names), or (N + 1, N)
    with a defer row; finite, zero diagonal, positive off-diagonal entries, defer costs >= 0.

    Args:
        cost: (N, N) or (N + 1, N) matrix, rows = predicted class (then defer), columns = true
            class.
        class_names: the model's classes, used for the shape and in error messages.

    Returns:
        ``cost`` as a float64 tensor.

    Raises:
        ValueError: naming the first offending entry.

    >>> validate_cost(torch.ones(2, 2) - torch.eye(2), ["a", "b"]).dtype
    torch.float64
    >>> validate_cost(torch.tensor([[0.0, -1.0], [1.0, 0.0]]), ["a", "b"])  # doctest: +ELLIPSIS
    Traceback (most recent call last):
    ...
    ValueError: cost matrix entry [0, 1] (predicted 'a', true 'b') is -1.0: off-diagonal ...
    >>> validate_cost(torch.tensor([[0.0, 1], [1, 0], [0.5, -1]]), ["a", "b"])  # doctest: +ELLIPSIS
    Traceback (most recent call last):
    ...
    ValueError: cost matrix entry [2, 1] (defer, true 'b') is -1.0: defer costs must be >= 0
    """
    cost = torch.as_tensor(cost, dtype=torch.float64)
    n = len(class_names)
    if cost.shape not in ((n, n), (n + 1, n)):
        raise ValueError(
            f"cost matrix must be {n}x{n} for {n} classes, got shape {tuple(cost.shape)}; with a "
            f"defer row it is {n + 1}x{n}"
        )
    diagonal = torch.eye(len(cost), n, dtype=torch.bool)
    defer = torch.zeros_like(diagonal)
    defer[n:] = True
    checks = (
        (~torch.isfinite(cost), "costs must be finite"),
        ((cost != 0) & diagonal, "the diagonal must be 0"),
        ((cost <= 0) & ~diagonal & ~defer, "off-diagonal costs must be > 0"),
        ((cost < 0) & defer, "defer costs must be >= 0"),
    )
    for bad, rule in checks:
        if bad.any():
            i, j = (int(v) for v in bad.nonzero()[0])
            row = "defer" if i == n else f"predicted {class_names[i]!r}"
            raise ValueError(
                f"cost matrix entry [{i}, {j}] ({row}, true {class_names[j]!r}) is "
                f"{cost[i, j].item()}: {rule}"
            )
    return cost


def has_defer_row(cost: torch.Tensor) -> bool:
    """Whether (..., R, N) matrices carry a defer row (R = N + 1; R = N: none)."""
    return cost.shape[-2] == cost.shape[-1] + 1


def with_defer(
    cost: torch.Tensor, defer: float | torch.Tensor, class_names: Sequence[str] | None = None
) -> torch.Tensor:
    """``cost`` with a defer row: (N, N) → (N + 1, N) (docs/definitions.md §14); a regional
    stack (R + 1, N, N) gets the same row in every matrix.

    Args:
        cost: (N, N) cost matrix, or (R + 1, N, N) regional stack.
        defer: the cost of deferring, for every true class (a number) or per true class ((N,)).
        class_names: names of the true classes in error messages (None: their indices).

    Raises:
        ValueError: ``cost`` is not square, ``defer`` has another shape, or a defer cost is
            negative, NaN or infinite.

    >>> with_defer(symmetric_cost(2), 0.25)
    tensor([[0.0000, 1.0000],
            [1.0000, 0.0000],
            [0.2500, 0.2500]], dtype=torch.float64)
    """
    cost = torch.as_tensor(cost, dtype=torch.float64)
    n = cost.shape[-1]
    if cost.shape[-2:] != (n, n) or cost.ndim not in (2, 3):
        raise ValueError(f"a defer row extends an NxN cost matrix, got shape {tuple(cost.shape)}")
    row = torch.as_tensor(defer, dtype=torch.float64, device=cost.device)
    if row.shape not in ((), (n,)):
        raise ValueError(f"defer costs must be a number or {n} numbers, got {tuple(row.shape)}")
    row = row.expand(n)
    bad = ~(torch.isfinite(row) & (row >= 0))
    if bad.any():
        j = int(bad.nonzero()[0])
        name = repr(class_names[j]) if class_names is not None else j
        raise ValueError(
            f"the defer cost of true class {name} is {row[j].item()}: defer costs must be "
            "finite and >= 0"
        )
    return torch.cat([cost, row.expand(*cost.shape[:-2], 1, n)], -2)


def load_cost(name_or_path: str | Path, class_names: Sequence[str] = CLASS_NAMES) -> torch.Tensor:
    """Load a preset (``robotistic``, ``altruistic``, ``egoistic``) or a YAML cost file.

    Three YAML formats (see the presets in ``configs/costs/`` and :data:`COST_FILE_KEYS`):

    * ``off_diagonal: λ`` — the symmetric matrix with every off-diagonal entry λ;
    * ``classes: [...]`` + ``matrix: N×N`` — a full matrix over named classes (any order);
    * ``aggregates`` + ``order`` + ``matrix`` (A×A), optionally ``epsilon`` (ε),
      ``suppressed_row_cost`` (M), ``suppressed_column_cost`` (s), which default to
      :data:`AGGREGATE_DEFAULTS` — expanded to N×N as in docs/definitions.md §2.

    Each may add ``name`` and ``defer`` (docs/definitions.md §14): a number, the cost of deferring
    whatever the true class, or a mapping from class names, aggregate names (files with
    aggregates) and ``default`` (every class not named otherwise) to the cost of deferring that
    true class; a class's own entry wins over its aggregate's.

    A file with ``regions:`` is a regional value system (docs/definitions.md §21,
    :func:`regional_of_spec`): the result is its (R + 1, M, N) stack.

    Returns:
        (N, N) float64 matrix, or (N + 1, N) with ``defer``, validated; (R + 1, N, N) or
        (R + 1, N + 1, N) for a regional file.

    Raises:
        ValueError: unknown preset; a malformed file, a missing or unknown key, unknown class,
            aggregate or region names, an invalid matrix, regions of different shapes: one line
            naming the file (and every class or the region at fault).
        FileNotFoundError: the path does not exist.

    >>> load_cost("robotistic").sum().item()    # 19 * 18 ones
    342.0
    >>> load_cost(COSTS_DIR / "street_person.yaml").shape    # regional: the default, RoIs 1 … 4
    torch.Size([5, 19, 19])
    """
    path, folder = Path(name_or_path), Path(name_or_path).parent
    if path.suffix not in (".yaml", ".yml"):
        if str(name_or_path) not in PRESETS:
            raise ValueError(
                f"unknown cost {str(name_or_path)!r}: expected one of {', '.join(PRESETS)} "
                "or a path to a .yaml file"
            )
        path, folder = COSTS_DIR / f"{name_or_path}.yaml", COSTS_DIR
    spec = read_yaml(path)
    try:
        if "regions" in spec or "default" in spec:
            cost = regional_of_spec(spec, folder, class_names)
        else:
            cost = cost_of_spec(spec, folder, class_names)
    except ValueError as err:  # one place names the file for every rule of the format
        raise ValueError(f"cost file {path}: {err}") from None
    return cost


def cost_name(name_or_path: str | Path) -> str:
    """The rule name of a cost: a preset's own, a file's ``name:`` (else its file name without
    the suffix).

    >>> cost_name("egoistic"), cost_name(COSTS_DIR / "street_person.yaml")
    ('egoistic', 'street_person')
    """
    path = Path(name_or_path)
    if path.suffix not in (".yaml", ".yml"):
        return str(name_or_path)
    name = read_yaml(path).get("name")
    return str(name) if isinstance(name, str | int | float) and str(name).strip() else path.stem


def save_cost(
    path: str | Path,
    cost: torch.Tensor,
    name: str,
    class_names: Sequence[str] = CLASS_NAMES,
    header: str = "",
) -> None:
    """Write ``cost`` as a full-matrix YAML file (a defer row as ``defer`` per class; one line
    per matrix row) that :func:`load_cost` reads back exactly; ``header``'s lines first, as YAML
    comments. A regional stack (R + 1, M, N) is written as ``default:`` and, for each RoI whose
    matrix differs from it, an entry of ``regions:``, each an inline full matrix; a stack whose
    matrices are all equal, as that one matrix (the same decisions, docs/definitions.md §21).

    >>> import tempfile
    >>> path = Path(tempfile.mkdtemp()) / "c.yaml"
    >>> save_cost(path, symmetric_cost(2), "two", ["a", "b"])
    >>> print(path.read_text().strip())
    name: two
    classes: [a, b]
    matrix:
    - [0.0, 1.0]
    - [1.0, 0.0]
    """
    if is_regional(cost):
        cost = validate_regional_cost(cost, class_names)
    if is_regional(cost) and any(not torch.equal(m, cost[0]) for m in cost[1:]):
        spec = {"name": name, "default": _full_spec(cost[0], class_names), "regions": {}}
        for r in range(1, len(cost)):
            if not torch.equal(cost[r], cost[0]):
                spec["regions"][ROI_NAMES[r]] = _full_spec(cost[r], class_names)
    else:
        plain = cost[0] if is_regional(cost) else cost
        spec = {"name": name} | _full_spec(validate_cost(plain, class_names), class_names)
    comments = "".join(f"# {line}".rstrip() + "\n" for line in header.splitlines())
    text = comments + yaml.dump(spec, Dumper=_RowDumper, sort_keys=False, width=1000)
    write_bytes(path, text.encode("utf-8"))


class _Row(list):
    """A matrix row or a list of names, written on one line (YAML's flow style)."""


class _RowDumper(yaml.SafeDumper):
    """``yaml.safe_dump`` with :class:`_Row` lists on one line each."""


_RowDumper.add_representer(
    _Row, lambda dumper, row: dumper.represent_sequence("tag:yaml.org,2002:seq", row, True)
)


def _full_spec(cost: torch.Tensor, class_names: Sequence[str]) -> dict:
    """The full-matrix form of a validated matrix (a defer row as ``defer`` per class)."""
    n = len(class_names)
    spec = {"classes": _Row(class_names), "matrix": [_Row(row) for row in cost[:n].tolist()]}
    if has_defer_row(cost):
        spec["defer"] = dict(zip(class_names, cost[n].tolist(), strict=True))
    return spec


def symmetric_cost(
    n: int, dtype: torch.dtype = torch.float64, device: torch.device | str | None = None
) -> torch.Tensor:
    """The robotistic matrix ``1 - I`` (every off-diagonal cost 1): its rule is argmax.

    Args:
        n: number of classes N.
        dtype: dtype of the result (float64 by default, like every cost matrix here).
        device: device of the result.

    Returns:
        (N, N) matrix.

    >>> symmetric_cost(3)
    tensor([[0., 1., 1.],
            [1., 0., 1.],
            [1., 1., 0.]], dtype=torch.float64)
    """
    return 1 - torch.eye(n, dtype=dtype, device=device)


def off_diagonal(cost: torch.Tensor) -> torch.Tensor:
    """The off-diagonal entries of (..., N, N) matrices, (..., N·(N − 1)) row by row; of a matrix
    with a defer row, those of its square part.

    >>> off_diagonal(torch.tensor([[0.0, 2], [3, 0], [0.5, 0.5]])).tolist()
    [2.0, 3.0]
    """
    n = cost.shape[-1]
    return cost[..., :n, :][..., ~torch.eye(n, dtype=torch.bool, device=cost.device)]


def cost_weights(cost: torch.Tensor) -> torch.Tensor:
    """Class weights from a cost matrix (rows predicted, columns true): the mean cost of missing
    class j, ``w_j = mean_{k≠j} C[k, j]`` over the class rows (a defer row counts nowhere),
    normalised to mean 1 over the classes (docs/definitions.md §16, §18).

    Args:
        cost: (N, N) matrix, or (N + 1, N) with a defer row.

    Returns:
        (N,) weights of ``cost``'s dtype.

    >>> cost = torch.tensor([[0, 1, 3], [1, 0, 3], [1, 1, 0]], dtype=torch.float64)
    >>> [round(w, 6) for w in cost_weights(cost).tolist()]
    [0.6, 0.6, 1.8]
    """
    n = cost.shape[-1]
    off = ~torch.eye(n, dtype=torch.bool, device=cost.device)
    missing = (cost[:n] * off).sum(0) / (n - 1)
    return missing / missing.mean()


def cost_or_symmetric(cost: torch.Tensor | None, n: int) -> torch.Tensor:
    """``cost``, or the (N, N) symmetric matrix (argmax) for None: how a rule without a matrix
    decides.

    >>> cost_or_symmetric(None, 2).tolist()
    [[0.0, 1.0], [1.0, 0.0]]
    """
    return symmetric_cost(n) if cost is None else cost


def rescale(cost: torch.Tensor) -> torch.Tensor:
    """Scale ``cost`` to unit mean off-diagonal cost (same decisions, different mixtures); a
    defer row is scaled alike. The mean is correctly rounded (``math.fsum``), so the scaled
    matrix is the same on every machine, whatever order a vectorised sum would take.

    >>> rescale(4 * load_cost("robotistic")).max().item()
    1.0
    """
    values = off_diagonal(cost).double()
    means = [
        math.fsum(row) / values.shape[-1] for row in values.reshape(-1, values.shape[-1]).tolist()
    ]
    mean = torch.tensor(means, dtype=cost.dtype, device=cost.device).reshape(values.shape[:-1])
    return cost / mean[..., None, None]


def mix_costs(vertices: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
    """Mixtures ``Σ_v w_v C_v``: vertices (V, R, N), weights (K, V) → (K, R, N) (R = N, or N + 1
    with defer rows), summed in the order of the vertices, ``(w_0 C_0 + w_1 C_1) + w_2 C_2``,
    one rounding per product and per sum on every machine (a matrix product may fuse them, and
    the explorer page mixes in this order).

    >>> mix_costs(torch.stack([load_cost("robotistic")] * 2), torch.tensor([[0.5, 0.5]])).shape
    torch.Size([1, 19, 19])
    """
    weights = torch.as_tensor(weights, dtype=torch.float64, device=vertices.device)
    vertices = vertices.to(torch.float64)
    mixed = weights[:, 0, None, None] * vertices[0]
    for v in range(1, vertices.shape[0]):
        mixed = mixed + weights[:, v, None, None] * vertices[v]
    return mixed


def barycentric_grid(step: float) -> torch.Tensor:
    """All barycentric weights (α, β, γ) on a grid of the given step, α+β+γ = 1.

    ``(1/h+1)(1/h+2)/2`` points, ordered by α descending, then β descending. Each weight is an
    exact ``i / n``, so the vertices are exactly (1, 0, 0), (0, 1, 0) and (0, 0, 1).

    >>> barycentric_grid(0.1).shape, barycentric_grid(0.05).shape
    (torch.Size([66, 3]), torch.Size([231, 3]))
    >>> barycentric_grid(0.5).tolist()[:3]
    [[1.0, 0.0, 0.0], [0.5, 0.5, 0.0], [0.5, 0.0, 0.5]]
    """
    n = steps_per_unit(step, "grid step")
    points = [(n - i - j, i, j) for i in range(n + 1) for j in range(n + 1 - i)]
    points.sort(key=lambda w: (-w[0], -w[1]))
    return torch.tensor(points, dtype=torch.float64) / n


# The keys of each form of a cost YAML file (docs/usage.md#cost-matrices): required, optional.
COST_FILE_KEYS: dict[str, tuple[tuple[str, ...], tuple[str, ...]]] = {
    "off_diagonal": (("off_diagonal",), ()),
    "classes": (("classes", "matrix"), ()),
    "aggregates": (
        ("aggregates", "order", "matrix"),
        ("epsilon", "suppressed_row_cost", "suppressed_column_cost", "suppressed"),
    ),
}
"""Per form (named by the key that chooses it): its required keys, and its optional keys besides
``name`` and ``defer``, which every form takes."""

AGGREGATE_DEFAULTS = {"epsilon": 0.1, "suppressed_row_cost": 1000.0, "suppressed_column_cost": 1.0}
"""ε, M and s of an aggregate cost file that leaves them out (docs/definitions.md §2)."""


def cost_of_spec(
    spec: dict, folder: Path | Traversable, class_names: Sequence[str]
) -> torch.Tensor:
    """The validated matrix of a cost file's mapping ``spec`` (see :func:`load_cost`); tables
    named in it are looked for in ``folder``.

    >>> cost_of_spec({"off_diagonal": 2}, COSTS_DIR, ["a", "b"]).tolist()
    [[0.0, 2.0], [2.0, 0.0]]
    >>> cost_of_spec({"classes": ["a", "b"]}, COSTS_DIR, ["a", "b"])
    Traceback (most recent call last):
    ...
    ValueError: missing key 'matrix': this form needs 'classes' and 'matrix'
    """
    form = next((key for key in COST_FILE_KEYS if key in spec), None)
    if form is None:
        raise ValueError("expected a key 'off_diagonal', 'aggregates' or 'classes'")
    required, optional = COST_FILE_KEYS[form]
    if form == "aggregates" and not {"order", "matrix"} & spec.keys():
        raise ValueError(
            "this is an aggregate table (which class is in which aggregate), not a cost matrix: "
            "a cost file names it under 'aggregates' with 'order' and 'matrix' (see the preset "
            "configs/costs/egoistic.yaml)"
        )
    missing = [key for key in required if key not in spec]
    if missing:
        raise ValueError(
            f"missing {_keys(missing)}: this form needs {_keys(required, 'and', noun=False)}"
        )
    unknown = sorted(set(spec) - {*required, *optional, "name", "defer"})
    if unknown:
        accepted = _keys([*required, *optional, "name", "defer"], noun=False)
        raise ValueError(f"unknown {_keys(unknown)}: this form takes {accepted}")
    if form == "off_diagonal":
        cost = _number(spec, "off_diagonal") * symmetric_cost(len(class_names))
    elif form == "aggregates":
        cost = expand_aggregates(spec, folder, class_names)
    else:
        cost = full_matrix(spec, class_names)
    if "defer" in spec:
        cost = with_defer(cost, defer_costs(spec, folder, class_names), class_names)
    return validate_cost(cost, class_names)


def is_regional(cost: torch.Tensor | None) -> bool:
    """Whether ``cost`` is a regional stack (R + 1, M, N) rather than one matrix (M, N)
    (docs/definitions.md §21).

    >>> is_regional(symmetric_cost(2)), is_regional(torch.stack([symmetric_cost(2)] * 5))
    (False, True)
    """
    return cost is not None and cost.ndim == 3


def regional_cost(
    default: torch.Tensor,
    regions: dict[int | str, torch.Tensor],
    class_names: Sequence[str] = CLASS_NAMES,
) -> torch.Tensor:
    """The (R + 1, M, N) stack of a regional value system (docs/definitions.md §21): index 0
    ``default``, index r the matrix ``regions`` gives RoI r (an id 1 … R or a name of
    ``classes.ROI_IDS``), the default where it gives none.

    Raises:
        ValueError: an unknown region, one named twice, an invalid matrix, or matrices of
            different shapes (a defer row on some only), naming the region.

    >>> stack = regional_cost(symmetric_cost(2), {"street": 2 * symmetric_cost(2)}, ["a", "b"])
    >>> stack.shape, stack[1, 0, 1].item(), stack[2, 0, 1].item()
    (torch.Size([5, 2, 2]), 2.0, 1.0)
    """
    default = validate_cost(default, class_names)
    stack = [default] * (NUM_ROIS + 1)
    given: dict[int, str] = {}
    for key, matrix in regions.items():
        r = region_id(key)
        if r in given:
            raise ValueError(f"regions {given[r]!r} and {key!r} are both RoI {r}")
        given[r] = key
        try:
            stack[r] = validate_cost(matrix, class_names)
        except ValueError as err:
            raise ValueError(f"region {key!r}: {err}") from None
        if stack[r].shape != default.shape:
            raise ValueError(
                f"region {key!r} has a {_shape(stack[r])} matrix and the default a "
                f"{_shape(default)} one: every matrix of a regional value system has a defer "
                "row, or none"
            )
    return torch.stack(stack)


def validate_regional_cost(
    stack: torch.Tensor, class_names: Sequence[str] = CLASS_NAMES
) -> torch.Tensor:
    """``stack`` as a float64 (R + 1, M, N) regional value system, each matrix valid
    (:func:`validate_cost`), R the RoIs of ``classes.ROI_NAMES``; ValueError naming the region.

    >>> validate_regional_cost(torch.stack([symmetric_cost(2)] * 5), ["a", "b"]).dtype
    torch.float64
    >>> validate_regional_cost(torch.stack([symmetric_cost(2)] * 3), ["a", "b"])
    Traceback (most recent call last):
    ...
    ValueError: a regional value system stacks 5 matrices (the default, then RoIs 1 … 4), got 3
    """
    stack = torch.as_tensor(stack, dtype=torch.float64)
    if stack.ndim != 3 or len(stack) != NUM_ROIS + 1:
        count = len(stack) if stack.ndim == 3 else f"shape {tuple(stack.shape)}"
        raise ValueError(
            f"a regional value system stacks {NUM_ROIS + 1} matrices (the default, then RoIs "
            f"1 … {NUM_ROIS}), got {count}"
        )
    for r, matrix in enumerate(stack):
        where = "the default" if r == 0 else f"region {ROI_NAMES[r]!r}"
        try:
            validate_cost(matrix, class_names)
        except ValueError as err:
            raise ValueError(f"{where}: {err}") from None
    return stack


def region_id(key: int | str) -> int:
    """The RoI id 1 … R of a key of ``regions:`` (``street``, ``roi1`` or ``1``).

    >>> region_id("street"), region_id("roi3"), region_id(4)
    (1, 3, 4)
    >>> region_id("image")
    Traceback (most recent call last):
    ...
    ValueError: region 'image' is the whole image (RoI 0): its matrix is 'default'
    """
    r = key if isinstance(key, int) and not isinstance(key, bool) else ROI_IDS.get(str(key))
    if r == 0:
        raise ValueError(f"region {key!r} is the whole image (RoI 0): its matrix is 'default'")
    if r is None or not 0 < r <= NUM_ROIS:
        names = ", ".join(ROI_NAMES[1:])
        raise ValueError(
            f"unknown region {key!r}: expected a RoI name ({names}), roi1 … roi{NUM_ROIS} or an "
            f"id 1 … {NUM_ROIS}"
        )
    return r


def regional_of_spec(
    spec: dict, folder: Path | Traversable, class_names: Sequence[str]
) -> torch.Tensor:
    """The validated (R + 1, M, N) stack of a regional cost file's mapping (docs/usage.md#regional
    value systems, docs/definitions.md §21).

    ``regions`` maps RoIs (:func:`region_id`) to matrices; ``default`` is the matrix of every
    other pixel. Each matrix is a preset's name, a .yaml file (beside the cost file) of a plain
    matrix, a mapping in any form of :data:`COST_FILE_KEYS` (with its own ``defer``, if any), or
    the N (or N + 1, a defer row last) rows of a matrix in the classes' order. Without
    ``default``, the file's own matrix (its keys of a form beside ``regions``) is the default,
    else the robotistic matrix. A ``defer`` beside ``regions`` gives a defer row to every matrix
    that has none.

    >>> regional_of_spec({"regions": {"street": {"off_diagonal": 2}}}, COSTS_DIR, ["a", "b"])[:2]
    tensor([[[0., 1.],
             [1., 0.]],
    <BLANKLINE>
            [[0., 2.],
             [2., 0.]]], dtype=torch.float64)
    >>> park = {"regions": {"park": "egoistic"}}
    >>> regional_of_spec(park, COSTS_DIR, CLASS_NAMES)  # doctest: +ELLIPSIS
    Traceback (most recent call last):
    ...
    ValueError: unknown region 'park': expected a RoI name (street, sidewalk, building, sky), ...
    """
    regions = spec.get("regions")
    if not isinstance(regions, dict) or not regions:
        raise ValueError(
            "'regions' must map RoIs (street, roi1 or 1, …) to matrices; 'default' goes with it"
        )
    own = {k: v for k, v in spec.items() if k not in ("regions", "default", "name", "defer")}
    form = [key for key in COST_FILE_KEYS if key in own]
    if "default" in spec and own:
        raise ValueError(
            f"the default matrix is 'default' or the file's own {_keys(sorted(own), 'and')}, "
            "not both"
        )
    if own and not form:
        raise ValueError(
            f"unknown {_keys(sorted(own))}: a regional file takes 'regions', 'default', 'name', "
            "'defer' and the keys of one matrix"
        )
    if "default" in spec:
        default = _entry_matrix(spec["default"], "'default'", folder, class_names)
    elif own:
        default = cost_of_spec(own, folder, class_names)
    else:
        default = symmetric_cost(len(class_names))
    matrices = {
        key: _entry_matrix(value, f"region {key!r}", folder, class_names)
        for key, value in regions.items()
    }
    if "defer" in spec:  # a defer row for every matrix without its own
        row = defer_costs(spec, folder, class_names)
        add = lambda m: m if has_defer_row(m) else with_defer(m, row, class_names)  # noqa: E731
        default, matrices = add(default), {key: add(m) for key, m in matrices.items()}
    return regional_cost(default, matrices, class_names)


def _entry_matrix(
    value: object, where: str, folder: Path | Traversable, class_names: Sequence[str]
) -> torch.Tensor:
    """The plain matrix of one entry of a regional file (see :func:`regional_of_spec`)."""
    try:
        if isinstance(value, str) and Path(value).suffix in (".yaml", ".yml"):
            path = Path(value) if Path(value).is_absolute() else folder / value
            inner = read_yaml(path)
            if "regions" in inner or "default" in inner:
                raise ValueError(f"{value} is a regional file itself: give a plain matrix")
            beside = path.parent if isinstance(path, Path) else folder
            return cost_of_spec(inner, beside, class_names)
        if isinstance(value, str):
            return load_cost(value, class_names)
        if isinstance(value, dict):
            return cost_of_spec(value, folder, class_names)
        if isinstance(value, list):
            return validate_cost(_rows(value, len(class_names)), class_names)
    except (ValueError, FileNotFoundError) as err:
        raise ValueError(f"{where}: {err}") from None
    raise ValueError(
        f"{where} must be a preset's name, a .yaml file, a cost mapping or the rows of a matrix, "
        f"got {value!r}"
    )


def _rows(values: list, n: int) -> torch.Tensor:
    """An inline matrix: N rows of N numbers, or N + 1 (a defer row last)."""
    try:
        matrix = torch.tensor(values, dtype=torch.float64)
    except (TypeError, ValueError, RuntimeError):
        matrix = None
    if matrix is None or matrix.shape not in ((n, n), (n + 1, n)):
        got = "" if matrix is None else f", got {_shape(matrix)}"
        raise ValueError(f"an inline matrix is {n} rows of {n} numbers (a defer row: {n + 1}){got}")
    return matrix


def _shape(cost: torch.Tensor) -> str:
    """``19x19``, ``20x19 (a defer row)``: a matrix's shape in messages."""
    text = "x".join(str(d) for d in cost.shape)
    return text + (" (a defer row)" if cost.ndim == 2 and has_defer_row(cost) else "")


def _keys(keys: Sequence[str], joint: str = "or", noun: bool = True) -> str:
    """``key 'a'`` / ``keys 'a', 'b'`` (noun), or ``'a' and 'b'`` (joint) for messages."""
    quoted = [repr(k) for k in keys]
    listed = quoted[0] if len(quoted) == 1 else f"{', '.join(quoted[:-1])} {joint} {quoted[-1]}"
    if not noun:
        return listed
    return f"key{'s' if len(keys) > 1 else ''} {', '.join(quoted)}"


def _classes(names: Sequence[str]) -> str:
    """``class 'a'`` / ``classes 'a', 'b'``: every class at fault, in messages."""
    return f"class{'es' if len(names) > 1 else ''} {', '.join(repr(n) for n in names)}"


def _number(spec: dict, key: str) -> float:
    """``spec[key]`` (else its default in :data:`AGGREGATE_DEFAULTS`) as a float."""
    value = spec.get(key, AGGREGATE_DEFAULTS.get(key))
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ValueError(f"{key!r} must be a number, got {value!r}")
    return float(value)


def read_yaml(path: Path | Traversable) -> dict:
    """The mapping of a YAML file; FileNotFoundError or ValueError naming ``path``."""
    if not path.is_file():
        raise FileNotFoundError(f"cost file not found: {path}")
    try:
        spec = yaml.safe_load(path.read_text())
    except yaml.YAMLError as err:
        raise ValueError(f"{path}: not valid YAML ({err.__class__.__name__})") from None
    if not isinstance(spec, dict):
        raise ValueError(f"{path}: expected a YAML mapping, got {type(spec).__name__}")
    return spec


def _as_matrix(values: object, size: int) -> torch.Tensor:
    try:
        matrix = torch.tensor(values, dtype=torch.float64)
    except (TypeError, ValueError, RuntimeError):
        raise ValueError(f"'matrix' must be a list of {size} rows of numbers") from None
    if matrix.shape != (size, size):
        raise ValueError(f"'matrix' must be {size}x{size}, got {tuple(matrix.shape)}")
    return matrix


def _positions(names: Sequence[str], class_names: Sequence[str], what: str) -> list[int]:
    unknown = [n for n in names if n not in class_names]
    if unknown:
        raise ValueError(
            f"{what}: unknown {_classes(unknown)}; expected one of: {', '.join(class_names)}"
        )
    return [list(class_names).index(n) for n in names]


def full_matrix(spec: dict, class_names: Sequence[str]) -> torch.Tensor:
    names = list(spec["classes"])
    _positions(names, class_names, "'classes'")
    missing = [c for c in class_names if c not in names]
    twice = sorted({n for n in names if names.count(n) > 1})
    if missing or twice:
        raise ValueError(
            f"'classes' must list each of the {len(class_names)} classes once"
            + (f"; missing {_classes(missing)}" if missing else "")
            + (f"; listed twice: {_classes(twice)}" if twice else "")
        )
    matrix = _as_matrix(spec["matrix"], len(names))
    order = _positions(names, class_names, "'classes'")
    cost = torch.empty_like(matrix)
    cost[torch.tensor(order)[:, None], torch.tensor(order)[None, :]] = matrix
    return cost


def _aggregate_table(spec: dict, folder: Path | Traversable) -> tuple[dict, list]:
    """The aggregates' classes by name, and the suppressed classes, of an aggregate cost file.

    ``aggregates`` names a table file (beside the cost file, else the packaged one of that
    name) or is the table itself: ``{aggregate: [classes]}``, with ``suppressed`` beside it.
    """
    table = spec["aggregates"]
    if isinstance(table, str):
        beside, packaged = folder / table, COSTS_DIR / table
        table = read_yaml(packaged if not beside.is_file() and packaged.is_file() else beside)
    elif isinstance(table, dict) and "aggregates" not in table:
        table = {"aggregates": table, "suppressed": spec.get("suppressed", [])}
    if not (isinstance(table, dict) and isinstance(table.get("aggregates"), dict)):
        raise ValueError(
            "'aggregates' must name a table file (e.g. aggregates.yaml) or map each aggregate "
            "to its classes"
        )
    return dict(table["aggregates"]), list(table.get("suppressed", []))


def expand_aggregates(
    spec: dict, folder: Path | Traversable, class_names: Sequence[str]
) -> torch.Tensor:
    groups, suppressed = _aggregate_table(spec, folder)
    order = list(spec["order"])
    if sorted(order) != sorted(groups):
        raise ValueError(f"'order' {order} must name each aggregate once: {', '.join(groups)}")
    agg_of = torch.full((len(class_names),), -1, dtype=torch.long)
    for a, name in enumerate(order):
        for i in _positions(groups[name], class_names, f"aggregate {name!r}"):
            if agg_of[i] >= 0:
                raise ValueError(f"class {class_names[i]!r} is in two aggregates")
            agg_of[i] = a
    sup = _positions(suppressed, class_names, "suppressed classes")
    unassigned = [class_names[i] for i in range(len(class_names)) if agg_of[i] < 0 and i not in sup]
    if unassigned:
        verb = "is" if len(unassigned) == 1 else "are"
        raise ValueError(f"{_classes(unassigned)} {verb} in no aggregate and not suppressed")
    matrix = _as_matrix(spec["matrix"], len(order))
    epsilon, row, column = (_number(spec, key) for key in AGGREGATE_DEFAULTS)
    safe = agg_of.clamp(min=0)
    cost = matrix[safe[:, None], safe[None, :]]
    cost[agg_of[:, None] == agg_of[None, :]] = epsilon
    cost[:, sup] = column  # s: sky as the true class
    cost[sup, :] = row  # M: predicting sky
    return cost.fill_diagonal_(0.0)


def defer_costs(
    spec: dict, folder: Path | Traversable, class_names: Sequence[str]
) -> float | torch.Tensor:
    """A cost file's ``defer``: a number, or (N,) from its mapping (see :func:`load_cost`)."""
    value = spec["defer"]
    if isinstance(value, bool) or not isinstance(value, (int, float, dict)):
        raise ValueError(
            "'defer' must be a number or a mapping from class names, aggregate names or "
            f"'default' to numbers, got {value!r}"
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
            raise ValueError(f"'defer' of {key!r} must be a number, got {number!r}")
        if key == "default":
            row[:] = number
        elif key in groups:
            row[_positions(groups[key], class_names, f"aggregate {key!r}")] = float(number)
        else:
            row[_positions([key], class_names, "'defer'")] = float(number)
    if row.isnan().any():
        missing = [class_names[int(i)] for i in row.isnan().nonzero()[:, 0]]
        raise ValueError(
            f"'defer' gives no cost for {_classes(missing)} (name them, their aggregates, or "
            "'default')"
        )
    return row
