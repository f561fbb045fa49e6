"""Deciding or deferring (docs/definitions.md §14): cost matrices with a defer row, against Chow's
closed form, a per-pixel loop over the N + 1 expected costs, and hand-written cost files."""

import math

import pytest
import torch
import yaml
from decision_inputs import VERTICES, defer_ties, smooth

from costseg.costs import (
    barycentric_grid,
    load_cost,
    mix_costs,
    rescale,
    save_cost,
    symmetric_cost,
    validate_cost,
    with_defer,
)
from costseg.decision import (
    decide,
    decide_mixtures,
    decide_mixtures_reference,
    decide_reference,
    explain,
)
from costseg.decision.dispatch import ENV, choose, reasons
from costseg.decision.inputs import Inputs
from costseg.rules.named import parse_rules
from costseg.rules.triangle import vertex_matrices

PATHS = ["torch", "reference"]  # the CPU paths that take a defer row (numba: refused, below)


@pytest.fixture(autouse=True)
def automatic(monkeypatch):
    monkeypatch.delenv(ENV, raising=False)
    monkeypatch.delenv("TRITON_INTERPRET", raising=False)


def loop(probs, cost, priors=None):
    """The rule written out: per pixel, ``Σ_k C[r, k] p_k / π_k`` for each of the N + 1 rows in
    float64 (the matrix as given, no shift), the first minimum; row N is 255."""
    b, n, h, w = probs.shape
    rows, p = cost.double().tolist(), probs.double().tolist()
    if priors is not None:
        priors = priors.double().view(n, 1, 1).expand(n, h, w) if priors.ndim == 1 else priors
        priors = priors.double().tolist()
    out = torch.empty(b, h, w, dtype=torch.long)
    for i in range(b):
        for y in range(h):
            for x in range(w):
                q = [p[i][k][y][x] for k in range(n)]
                if priors is not None:
                    q = [q[k] / priors[k][y][x] for k in range(n)]
                costs = [sum(row[k] * q[k] for k in range(n)) for row in rows]
                best = min(range(len(costs)), key=costs.__getitem__)
                out[i, y, x] = 255 if best == n else best
    return out


def random_probs(shape, seed, scale=3.0):
    """Softmax of independent random logits: every pixel its own."""
    gen = torch.Generator().manual_seed(seed)
    return (scale * torch.randn(shape, generator=gen)).softmax(1)


def random_cost(n, seed, defer_scale):
    """(N + 1, N): off-diagonal costs log-uniform in [0.1, 10], a defer row in [0, defer_scale]."""
    gen = torch.Generator().manual_seed(seed)
    cost = 10 ** (2 * torch.rand(n, n, generator=gen, dtype=torch.float64) - 1)
    defer = defer_scale * torch.rand(n, generator=gen, dtype=torch.float64)
    return with_defer(cost.fill_diagonal_(0.0), defer)


# --- Chow's rule ---------------------------------------------------------------------------


@pytest.mark.parametrize("path", PATHS)
@pytest.mark.parametrize("c", [0.0, 0.1, 0.35, 0.6, 0.7, 1.0])
def test_symmetric_matrix_with_a_scalar_defer_cost_is_chows_rule(path, c):
    probs = smooth((2, 7, 16, 16), seed=1, scale=2.0)
    top = probs.double().max(1)
    away = (top.values - (1 - c)).abs() > 1e-6  # off the rule's own tie
    chow = torch.where(top.values < 1 - c, 255, top.indices)
    got = decide(probs, with_defer(symmetric_cost(7), c), path=path)
    assert torch.equal(got[away], chow[away])
    if 0 < c < 1:
        assert 0 < (chow[away] == 255).float().mean() < 1  # both outcomes occur


@pytest.mark.parametrize("path", PATHS)
def test_a_class_wins_its_tie_with_deferring(path):
    # Dyadic values, exact in float32 and in every sum: max p = 1 - c exactly.
    probs = torch.tensor([[0.5, 0.25, 0.25], [0.375, 0.375, 0.25], [0.25, 0.25, 0.5]])
    probs = probs.t().reshape(1, 3, 1, 3)
    assert decide(probs, with_defer(symmetric_cost(3), 0.5), path=path).tolist() == [[[0, 255, 2]]]
    assert decide(probs, with_defer(symmetric_cost(3), 0.625), path=path).tolist() == [[[0, 0, 2]]]
    # the defer row equal to class 1's row: class 1 wins wherever it would, never 255
    cost = torch.tensor([[0.0, 2, 1], [1, 0, 3], [4, 1, 0]], dtype=torch.float64)
    got = decide(probs, torch.cat([cost, cost[1:2]]), path=path)
    assert torch.equal(got, decide(probs, cost, path=path))


# --- against the loop --------------------------------------------------------------------------


@pytest.mark.parametrize("path", [*PATHS, None])
@pytest.mark.parametrize("priors", ["none", "global", "pixel-wise"])
@pytest.mark.parametrize(("n", "seed", "defer_scale"), [(5, 0, 1.0), (16, 1, 1.0), (2, 2, 0.2)])
def test_decide_equals_the_loop_over_the_expected_costs(path, priors, n, seed, defer_scale):
    gen = torch.Generator().manual_seed(seed)
    probs = random_probs((2, n, 8, 12), seed, scale=2.0)
    prior = {
        "none": None,
        "global": torch.rand(n, generator=gen, dtype=torch.float64) + 0.05,
        "pixel-wise": torch.rand(n, 8, 12, generator=gen) + 0.05,
    }[priors]
    cost = random_cost(n, seed, defer_scale)
    expected = loop(probs, cost, prior)
    assert 0 < (expected == 255).float().mean() < 1
    assert torch.equal(decide(probs, cost, prior, path=path), expected)
    assert torch.equal(decide_reference(probs, cost, prior), expected)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float16, torch.bfloat16])
def test_the_torch_path_equals_the_reference_where_deferring_nearly_ties(dtype):
    cost = with_defer(VERTICES[1], torch.linspace(0.5, 20, 19, dtype=torch.float64))
    probs = defer_ties(cost, 60, seed=4).to(dtype)
    got = decide(probs, cost, path="torch")
    assert torch.equal(got, decide_reference(probs, cost))
    assert 0 < (got == 255).float().mean() < 1


@pytest.mark.parametrize("path", [*PATHS, None])
@pytest.mark.parametrize("priors", [None, "global"])
def test_mixtures_with_defer_rows_equal_the_loop_over_mixed_matrices(path, priors):
    n = 6
    probs = random_probs((1, n, 8, 10), seed=5)
    prior = None if priors is None else torch.linspace(0.5, 1.5, n, dtype=torch.float64)
    vertices = torch.stack([random_cost(n, seed, defer_scale=s) for seed, s in [(7, 0.5), (8, 3)]])
    vertices = torch.cat([vertices, with_defer(symmetric_cost(n), 0.3)[None]])
    weights = barycentric_grid(0.25)
    got = decide_mixtures(probs, vertices, weights, prior, path=path)
    assert got.dtype == torch.uint8
    expected = torch.stack([loop(probs, c, prior) for c in mix_costs(vertices, weights)], 1)
    assert (expected == 255).any() and (expected != 255).any()
    assert torch.equal(got.long(), expected)
    assert torch.equal(decide_mixtures_reference(probs, vertices, weights, prior), expected)


def test_mixtures_near_ties_of_deferring_equal_the_reference():
    vertices = torch.stack(
        [with_defer(v, c) for v, c in zip(VERTICES, [0.4, 3.0, 30.0], strict=True)]
    )
    weights = barycentric_grid(0.25)
    probs = torch.cat(
        [defer_ties(m, 14, seed=k) for k, m in enumerate(mix_costs(vertices, weights))], 3
    )
    got = decide_mixtures(probs, vertices, weights, path="torch").long()
    assert torch.equal(got, decide_mixtures_reference(probs, vertices, weights))


def test_a_defer_row_needs_at_most_255_classes():
    probs = torch.full((1, 255, 1, 2), 1 / 255)
    probs[0, :, 0, 0] = 0.1 / 254
    probs[0, 3, 0, 0] = 0.9
    cost = with_defer(symmetric_cost(255), 0.5)
    assert decide(probs, cost).tolist() == [[[3, 255]]]  # 255: deferred, no class
    wide = torch.full((1, 256, 1, 1), 1 / 256)
    too_many = with_defer(symmetric_cost(256), 0.5)
    for call in (decide, decide_reference):
        with pytest.raises(ValueError, match="at most 255 classes"):
            call(wide, too_many)
    with pytest.raises(ValueError, match="at most 255 classes"):
        decide_mixtures(wide, too_many[None], torch.ones(1, 1))
    with pytest.raises(ValueError, match=r"got \(5, 3\); with a defer row it is 4x3"):
        decide(torch.rand(1, 3, 1, 1), torch.zeros(5, 3))


# --- the dispatcher ----------------------------------------------------------------------------


def test_the_dispatcher_sends_a_defer_row_of_mixtures_past_numba():
    big = Inputs((1, 19, 1024, 1024), torch.device("cpu"), torch.float32, defer=True)
    assert choose(big).NAME == "numba"  # one rule with a defer row: the single-rule kernel
    sweep = Inputs((1, 19, 64, 64), torch.device("cpu"), torch.float32, False, 3, 66, True)
    assert choose(sweep).NAME == "torch"
    assert any(r.startswith("a defer row in mixtures: ") for r in reasons("numba", sweep))
    for inputs in (big, sweep):
        assert not any("defer" in r for r in reasons("triton", inputs))  # the kernel takes it
        assert reasons("torch", inputs) == [] and reasons("reference", inputs) == []
    cuda = Inputs((1, 19, 64, 64), torch.device("cuda"), torch.float32, defer=True)
    assert not any("defer" in r for r in reasons("triton", cuda))
    probs = smooth((1, 19, 4, 5), seed=0)
    cost = with_defer(VERTICES[1], 5.0)
    assert decide(probs, cost, path="numba").equal(decide_reference(probs, cost))
    with pytest.raises(ValueError, match=r"'numba' cannot take .*a defer row in mixtures: "):
        decide_mixtures(probs, cost.expand(3, -1, -1), barycentric_grid(0.5), path="numba")
    text = explain(probs, cost)
    assert "a defer row: path 'torch'" in text.splitlines()[0]
    assert "numba: not chosen: 20 pixels per image" in text  # it could: only the size says no
    assert "defer" not in explain(probs, VERTICES, weights=barycentric_grid(0.5))


def test_inputs_of_the_matrices_say_whether_they_defer():
    probs = torch.rand(1, 3, 2, 2)
    assert not Inputs.of(probs, None, symmetric_cost(3)[None]).defer
    assert Inputs.of(probs, None, with_defer(symmetric_cost(3), 1.0)[None]).defer


# --- cost matrices and files -------------------------------------------------------------------


def test_with_defer_appends_a_row_and_refuses_bad_costs():
    cost = symmetric_cost(3)
    expected = torch.tensor([[0, 1, 1], [1, 0, 1], [1, 1, 0], [0.5, 0.5, 0.5]], dtype=torch.float64)
    assert torch.equal(with_defer(cost, 0.5), expected)
    row = torch.tensor([0.0, 2, 3])
    assert torch.equal(with_defer(cost, row)[3], row.double())
    for bad in (-0.1, math.nan, math.inf, torch.tensor([1.0, -1, 1])):
        with pytest.raises(ValueError, match="finite and >= 0"):
            with_defer(cost, bad)
    with pytest.raises(ValueError, match="true class 'b'"):
        with_defer(cost, torch.tensor([1.0, math.nan, 1]), ["a", "b", "c"])
    with pytest.raises(ValueError, match="a number or 3 numbers"):
        with_defer(cost, torch.ones(4))
    with pytest.raises(ValueError, match="NxN"):
        with_defer(with_defer(cost, 1.0), 1.0)


def test_validate_accepts_a_defer_row_and_names_a_bad_one():
    names = ["a", "b"]
    cost = torch.tensor([[0.0, 1], [2, 0], [0, 0.5]])
    assert validate_cost(cost, names).shape == (3, 2)  # a defer cost of 0 is valid
    with pytest.raises(ValueError, match=r"\[2, 0\] \(defer, true 'a'\) is -1.0: defer costs"):
        validate_cost(torch.tensor([[0.0, 1], [2, 0], [-1, 0.5]]), names)
    with pytest.raises(ValueError, match=r"\[2, 1\] \(defer, true 'b'\) is nan: costs must be"):
        validate_cost(torch.tensor([[0.0, 1], [2, 0], [1, math.nan]]), names)
    with pytest.raises(ValueError, match=r"got shape \(4, 2\); with a defer row it is 3x2"):
        validate_cost(torch.zeros(4, 2), names)


def write(tmp_path, spec, name="cost.yaml"):
    path = tmp_path / name
    path.write_text(yaml.safe_dump(spec))
    return path


NAMES = ["a", "b", "c", "d"]
TABLE = {"aggregates": {"ab": ["a", "b"], "c": ["c"]}, "suppressed": ["d"]}
AGGREGATE_FILE = {
    "aggregates": TABLE,
    "order": ["ab", "c"],
    "matrix": [[0, 2], [3, 0]],
    "epsilon": 0.1,
    "suppressed_row_cost": 1000,
    "suppressed_column_cost": 1,
}


def test_cost_files_with_defer_load_to_the_extended_matrix(tmp_path):
    scalar = load_cost(write(tmp_path, {"off_diagonal": 2.0, "defer": 0.3}), NAMES)
    assert torch.equal(scalar, with_defer(2 * symmetric_cost(4), 0.3))
    full = {
        "classes": ["b", "a", "d", "c"],
        "matrix": (4 * symmetric_cost(4)).tolist(),
        "defer": {"c": 0.7, "a": 0.1, "default": 2},
    }
    cost = load_cost(write(tmp_path, full), NAMES)
    assert cost[4].tolist() == [0.1, 2.0, 0.7, 2.0]
    spec = {**AGGREGATE_FILE, "defer": {"ab": 5, "b": 0.5, "c": 1.5, "d": 0}}
    expected = torch.tensor(
        [
            [0, 0.1, 2, 1],
            [0.1, 0, 2, 1],
            [3, 3, 0, 1],
            [1000, 1000, 1000, 0],
            [5, 0.5, 1.5, 0],  # a from its aggregate, b its own entry
        ],
        dtype=torch.float64,
    )
    assert torch.equal(load_cost(write(tmp_path, spec), NAMES), expected)


@pytest.mark.parametrize(
    ("defer", "message"),
    [
        (-0.5, "defer costs must be finite and >= 0"),
        (float("nan"), "defer costs must be finite and >= 0"),
        ("high", "'defer' must be a number or a mapping"),
        (True, "'defer' must be a number or a mapping"),
        ({"a": 1, "b": 1}, "no cost for classes 'c', 'd'"),
        ({"ab": 1, "x": 1, "default": 1}, "unknown class 'x'"),
        ({"default": "1"}, "'defer' of 'default' must be a number"),
        ({"c": -1, "default": 1}, "true class 'c' is -1.0"),
    ],
)
def test_bad_defer_entries_are_refused(tmp_path, defer, message):
    with pytest.raises(ValueError, match=message):
        load_cost(write(tmp_path, {**AGGREGATE_FILE, "defer": defer}), NAMES)


def test_a_saved_defer_row_loads_back_exactly(tmp_path):
    cost = with_defer(load_cost("egoistic"), torch.linspace(0.1, 3.7, 19, dtype=torch.float64))
    save_cost(tmp_path / "c.yaml", cost, "deferring")
    assert torch.equal(load_cost(tmp_path / "c.yaml"), cost)


def test_rescale_scales_the_defer_row_alike():
    cost = with_defer(4 * symmetric_cost(3), 2.0)
    assert torch.equal(rescale(cost), with_defer(symmetric_cost(3), 0.5))
    assert torch.equal(rescale(cost[None].expand(2, -1, -1))[1], rescale(cost))


def test_named_rules_take_a_defer_row_from_the_file_or_from_defer(tmp_path):
    deferring = str(write(tmp_path, {"off_diagonal": 1.0, "defer": 0.5}, "r.yaml"))
    assert torch.equal(parse_rules([deferring])[0].cost, with_defer(symmetric_cost(19), 0.5))
    rules = parse_rules(["egoistic", "ml"], defer=0.25)
    assert [r.defers for r in rules] == [True, True]
    assert torch.equal(rules[0].cost, with_defer(load_cost("egoistic"), 0.25))
    assert rules[1].priors_alpha == 1.0
    assert torch.equal(rules[1].cost, with_defer(symmetric_cost(19), 0.25))
    with pytest.raises(
        ValueError, match=r"--defer with .*r\.yaml, which has a defer row of its own: leave it out"
    ):
        parse_rules([deferring], defer=0.25)
    with pytest.raises(ValueError, match="a vertex of the triangle cannot have a defer row"):
        vertex_matrices([deferring, "altruistic", "egoistic"])
