"""Cost matrices against docs/definitions.md §2, block by block, and every invalid input."""

import itertools

import pytest
import torch
import yaml

from costseg.classes import CLASS_NAMES
from costseg.costs import (
    barycentric_grid,
    load_cost,
    mix_costs,
    rescale,
    save_cost,
    symmetric_cost,
    validate_cost,
)

# docs/definitions.md §2, retyped here on purpose: the test must not read the files it checks.
AGGREGATES = {
    "road": ["road"],
    "flat": ["sidewalk", "terrain"],
    "static": ["building", "wall", "fence", "pole", "motorcycle", "bicycle", "vegetation"],
    "info": ["traffic light", "traffic sign"],
    "human": ["person", "rider"],
    "dynamic": ["car", "truck", "bus", "train"],
}
ORDER = list(AGGREGATES)
C_A = [
    [0, 1, 10, 100, 1000, 100],
    [1, 0, 10, 100, 1000, 100],
    [1, 1, 0, 100, 100, 10],
    [1, 1, 1, 0, 1000, 100],
    [1, 1, 1, 100, 0, 10],
    [1, 1, 1, 100, 1000, 0],
]
C_E = [
    [0, 1, 1000, 100, 10, 100],
    [1, 0, 1000, 100, 10, 100],
    [10, 1, 0, 1000, 1, 10],
    [10, 1, 1000, 0, 1, 10],
    [10, 1, 1000, 100, 0, 100],
    [10, 10, 1000, 100, 100, 0],
]
AGG_OF = {c: a for a, names in AGGREGATES.items() for c in names}


@pytest.mark.parametrize(("name", "table"), [("altruistic", C_A), ("egoistic", C_E)])
def test_preset_matches_spec_entry_by_entry(name, table):
    cost = load_cost(name)
    for i, j in itertools.product(range(19), range(19)):
        pred, true = CLASS_NAMES[i], CLASS_NAMES[j]
        if i == j:
            expected = 0.0
        elif pred == "sky":
            expected = 1000.0  # M: sky's row
        elif true == "sky":
            expected = 1.0  # s: sky's column
        elif AGG_OF[pred] == AGG_OF[true]:
            expected = 0.1  # epsilon inside an aggregate
        else:
            expected = table[ORDER.index(AGG_OF[pred])][ORDER.index(AGG_OF[true])]
        assert cost[i, j].item() == pytest.approx(expected), (pred, true)


def test_robotistic_is_the_symmetric_matrix():
    assert torch.equal(load_cost("robotistic"), 1 - torch.eye(19, dtype=torch.float64))


@pytest.mark.parametrize("name", ["robotistic", "altruistic", "egoistic"])
def test_yaml_round_trip(tmp_path, name):
    cost = load_cost(name)
    save_cost(tmp_path / "c.yaml", cost, name)
    assert torch.equal(load_cost(tmp_path / "c.yaml"), cost)


def test_full_matrix_in_another_class_order(tmp_path):
    names = list(reversed(CLASS_NAMES))
    matrix = torch.arange(361, dtype=torch.float64).view(19, 19) + 1
    matrix.fill_diagonal_(0)
    path = tmp_path / "rev.yaml"
    path.write_text(yaml.safe_dump({"classes": names, "matrix": matrix.tolist()}))
    cost = load_cost(path)
    # cost[person, car] must be the file's entry at (row "person", column "car").
    i, j = names.index("person"), names.index("car")
    assert cost[11, 13].item() == matrix[i, j].item()


def _bad(entry_value, i=2, j=5):
    cost = 1 - torch.eye(19, dtype=torch.float64)
    cost[i, j] = entry_value
    return cost


@pytest.mark.parametrize(
    ("cost", "message"),
    [
        (_bad(-1.0), r"entry \[2, 5\] \(predicted 'building', true 'pole'\) is -1.0: off-diag"),
        (_bad(0.0), r"entry \[2, 5\].* off-diagonal costs must be > 0"),
        (_bad(float("nan")), r"entry \[2, 5\].* costs must be finite"),
        (_bad(float("inf")), r"entry \[2, 5\].* costs must be finite"),
        (_bad(0.5, 3, 3), r"entry \[3, 3\] \(predicted 'wall', true 'wall'\).* diagonal must be 0"),
        (torch.ones(18, 18), r"must be 19x19 for 19 classes, got shape \(18, 18\)"),
        (torch.ones(19), r"must be 19x19"),
    ],
)
def test_invalid_matrices_name_the_entry(cost, message):
    with pytest.raises(ValueError, match=message):
        validate_cost(cost)


def _write(tmp_path, spec, name="c.yaml"):
    path = tmp_path / name
    path.write_text(yaml.safe_dump(spec))
    return path


def _aggregate_spec(**changes):
    spec = {
        "aggregates": {"aggregates": AGGREGATES, "suppressed": ["sky"]},
        "order": ORDER,
        "matrix": C_A,
        "epsilon": 0.1,
        "suppressed_row_cost": 1000,
        "suppressed_column_cost": 1,
    }
    spec.update(changes)
    return spec


def test_inline_aggregate_file_equals_preset(tmp_path):
    assert torch.equal(load_cost(_write(tmp_path, _aggregate_spec())), load_cost("altruistic"))


def test_aggregate_table_named_inline_or_packaged(tmp_path):
    """``aggregates: aggregates.yaml`` outside the repository falls back to the packaged table;
    a file of that name beside the cost file wins; the bare mapping works inline."""
    paper = load_cost("altruistic")
    outside = _write(tmp_path, _aggregate_spec(aggregates="aggregates.yaml"))
    assert torch.equal(load_cost(outside), paper)
    inline = _aggregate_spec(aggregates=AGGREGATES, suppressed=["sky"])
    assert torch.equal(load_cost(_write(tmp_path, inline, "inline.yaml")), paper)
    moved = {**AGGREGATES, "flat": ["sidewalk"], "static": [*AGGREGATES["static"], "terrain"]}
    _write(tmp_path, {"aggregates": moved, "suppressed": ["sky"]}, "aggregates.yaml")
    own = load_cost(outside)
    terrain, sidewalk, road = (CLASS_NAMES.index(c) for c in ("terrain", "sidewalk", "road"))
    assert own[road, terrain] == 10 and paper[road, terrain] == 1  # road -> static, not flat
    assert own[road, sidewalk] == paper[road, sidewalk] == 1


@pytest.mark.parametrize(
    ("spec", "message"),
    [
        (_aggregate_spec(order=[*ORDER[:-1], "vehicles"]), r"'order' .* must name each aggregate"),
        (
            _aggregate_spec(aggregates={"aggregates": {**AGGREGATES, "human": ["person", "ridr"]}}),
            r"aggregate 'human': unknown class 'ridr'",
        ),
        (_aggregate_spec(aggregates={"aggregates": AGGREGATES}), r"class 'sky' is in no aggregate"),
        (_aggregate_spec(matrix=C_A[:5]), r"'matrix' must be 6x6, got \(5, 6\)"),
        (_aggregate_spec(epsilon=0), r"entry \[1, 9\].* off-diagonal costs must be > 0"),
        (
            {"classes": [*CLASS_NAMES[:-1], "scooter"], "matrix": [[1] * 19] * 19},
            r"unknown class 'scooter'",
        ),
        (
            {"classes": [*CLASS_NAMES[:-2], "road"], "matrix": [[1] * 18] * 18},
            r"missing classes 'motorcycle', 'bicycle'; listed twice: class 'road'$",
        ),
        (
            _aggregate_spec(aggregates={"aggregates": {**AGGREGATES, "human": []}}),
            r"classes 'sky', 'person', 'rider' are in no aggregate",
        ),
        ({"classes": list(CLASS_NAMES)}, r"missing key 'matrix': this form needs 'classes' and"),
        (
            {k: v for k, v in _aggregate_spec().items() if k != "order"},
            r"missing key 'order': this form needs 'aggregates', 'order' and 'matrix'$",
        ),
        (_aggregate_spec(epsilom=0.5), r"unknown key 'epsilom': this form takes .*'epsilon'"),
        ({"off_diagonal": 1, "matrix": []}, r"unknown key 'matrix': this form takes 'off_di"),
        (_aggregate_spec(epsilon="small"), r"'epsilon' must be a number, got 'small'$"),
        ({"off_diagonal": None}, r"'off_diagonal' must be a number, got None$"),
        ({"classes": list(CLASS_NAMES), "matrix": [[0] * 19] * 18}, r"must be 19x19, got \(18,"),
        ({"matrix": []}, r"expected a key 'off_diagonal', 'aggregates' or 'classes'"),
    ],
)
def test_invalid_yaml_files(tmp_path, spec, message):
    path = _write(tmp_path, spec)
    with pytest.raises(ValueError, match=message) as refused:
        load_cost(path)
    assert str(refused.value).startswith(f"cost file {path}: ")  # the file, on one line
    assert "\n" not in str(refused.value)


@pytest.mark.parametrize(
    ("left_out", "value"),
    [("epsilon", 0.1), ("suppressed_row_cost", 1000), ("suppressed_column_cost", 1)],
)
def test_optional_aggregate_keys_take_the_documented_defaults(tmp_path, left_out, value):
    """docs/definitions.md §2: ε = 0.1, M = 1000, s = 1 when a file leaves them out."""
    given = _aggregate_spec(**{left_out: value})
    without = {k: v for k, v in given.items() if k != left_out}
    assert torch.equal(
        load_cost(_write(tmp_path, without)), load_cost(_write(tmp_path, given, "g.yaml"))
    )
    bare = {
        k: v
        for k, v in given.items()
        if k not in ("epsilon", "suppressed_row_cost", "suppressed_column_cost")
    }
    assert torch.equal(load_cost(_write(tmp_path, bare, "bare.yaml")), load_cost("altruistic"))


def test_unknown_preset_and_missing_file(tmp_path):
    with pytest.raises(ValueError, match="expected one of robotistic, altruistic, egoistic"):
        load_cost("selfish")
    with pytest.raises(FileNotFoundError, match="cost file not found"):
        load_cost(tmp_path / "nope.yaml")
    (tmp_path / "broken.yaml").write_text("matrix: [1, 2\n")
    with pytest.raises(ValueError, match="not valid YAML"):
        load_cost(tmp_path / "broken.yaml")


def test_symmetric_cost():
    cost = symmetric_cost(4, dtype=torch.float32)
    assert cost.dtype == torch.float32
    assert torch.equal(cost, torch.ones(4, 4) - torch.eye(4))
    assert torch.equal(symmetric_cost(19), load_cost("robotistic"))


@pytest.mark.parametrize(("step", "count"), [(1.0, 3), (0.5, 6), (0.1, 66), (0.05, 231)])
def test_barycentric_grid(step, count):
    grid = barycentric_grid(step)
    assert grid.shape == (count, 3)
    assert torch.allclose(grid.sum(1), torch.ones(count, dtype=torch.float64))
    assert (grid >= 0).all()
    assert len({tuple(r) for r in grid.tolist()}) == count
    for vertex in torch.eye(3, dtype=torch.float64):
        assert (grid == vertex).all(1).any()


@pytest.mark.parametrize("step", [0, -0.1, 0.3, 2.0])
def test_barycentric_grid_rejects_bad_steps(step):
    with pytest.raises(ValueError, match="grid step must be 1/n"):
        barycentric_grid(step)


def test_mix_and_rescale():
    vertices = torch.stack([load_cost(n) for n in ("robotistic", "altruistic", "egoistic")])
    mixed = mix_costs(vertices, torch.tensor([[0.2, 0.3, 0.5]]))[0]
    assert torch.allclose(mixed, 0.2 * vertices[0] + 0.3 * vertices[1] + 0.5 * vertices[2])
    off = ~torch.eye(19, dtype=torch.bool)
    assert torch.allclose(rescale(vertices)[:, off].mean(1), torch.ones(3, dtype=torch.float64))


def test_a_cost_file_names_its_rule_and_writes_a_row_per_line(tmp_path):
    """``--cost FILE`` takes the file's ``name:`` (a designed file says ``designed``), its file
    name where it has none or where two files share one; a saved matrix is one line per row."""
    from costseg.rules import parse_rules

    first, second, plain = tmp_path / "a_cost.yaml", tmp_path / "b_cost.yaml", tmp_path / "c.yaml"
    save_cost(first, load_cost("egoistic"), "designed")
    save_cost(second, load_cost("altruistic"), "designed")
    plain.write_text("off_diagonal: 2\n")
    assert [r.name for r in parse_rules([str(first), str(plain)])] == ["designed", "c"]
    assert [r.name for r in parse_rules([str(first), str(second)])] == ["a_cost", "b_cost"]
    lines = first.read_text().splitlines()
    assert len(lines) == 3 + 19 and lines[3].startswith("- [0.0, 1.0, 1000.0")
