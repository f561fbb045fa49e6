"""The table of analyses: each entry resolves typed, frozen settings once from the options (None
when not asked for), fits run in an order their declared dependencies give whatever the table's
order, and what a fit provides is applied by the loop, the rule groups frozen before the
reported images."""

import dataclasses
import itertools
from types import SimpleNamespace

import pytest

from costseg.calibration.scaling import Scaling
from costseg.evaluation import settings as s
from costseg.evaluation.analyses import ANALYSES, Context, Provided, fit_order, wanted
from costseg.options import EvalOptions
from costseg.rules import named_group, parse_rules, rules_group, temperature_group

EVERYTHING = EvalOptions(
    calibrate="temperature", meta=True, save_segments=True, sweep=0.5,
    target=["person:roi1:recall>=0.9"], maximize="person:roi1:precision", guarantee=0.2,
    design="lagrangian", require=["person:roi1:recall>=0.8", "car:roi1:recall>=0.7"],
    design_delta=0.1, save_probs=True, anomalies=True, conformal=0.2, explorer=True,
    monitor_require=["person:roi1:recall>=0.8"],
)  # fmt: skip


def test_every_entry_resolves_frozen_settings_once_asked_for():
    given = dict(wanted(EVERYTHING))
    assert {e.module for e in given} == {e.module for e in ANALYSES}
    for entry, settings in given.items():
        assert dataclasses.is_dataclass(settings), entry.module
        field = next(iter(dataclasses.fields(settings)), None)
        if field is not None:
            with pytest.raises(dataclasses.FrozenInstanceError):
                setattr(settings, field.name, None)
    asked = {e.module for e, _ in wanted(EvalOptions())}
    assert asked == {"metrics", "calibration", "examples"}


def test_the_sweep_choice_and_the_design_are_their_own_settings():
    given = {e.module: v for e, v in wanted(EVERYTHING)}
    assert given["choice"] == s.SweepChoice(
        "person:roi1:recall>=0.9", "person:roi1:precision", 0.2, "bonferroni"
    )
    assert given["guarantee"] == given["choice"]
    design = given["design"]
    assert design.requirements == ("person:roi1:recall>=0.8", "car:roi1:recall>=0.7")
    assert (design.delta, design.space, design.maximize) == (0.1, "lagrangian", None)
    unguaranteed = dataclasses.replace(EVERYTHING, guarantee=None)
    choice_only = {e.module: v for e, v in wanted(unguaranteed)}
    assert "guarantee" not in choice_only and choice_only["choice"].delta is None


def test_fits_follow_their_dependencies_in_any_table_order():
    fitting = [e for e in ANALYSES if e.module in ("scaling", "segments", "guarantee", "design")]
    for order in itertools.permutations(fitting):
        modules = [e.module for e in fit_order(list(order))]
        assert modules.index("scaling") < modules.index("segments") < modules.index("guarantee")
        assert modules.index("scaling") < modules.index("design")


def test_fit_order_refuses_a_cycle_and_an_unknown_dependency():
    a = dataclasses.replace(ANALYSES[0], module="scaling", after=("metrics",))
    b = dataclasses.replace(ANALYSES[1], module="metrics", after=("scaling",))
    with pytest.raises(ValueError, match="wait on each other"):
        fit_order([a, b])
    with pytest.raises(ValueError, match="unknown"):
        fit_order([dataclasses.replace(ANALYSES[0], after=("nothing",))])


def test_what_a_fit_provides_is_applied_and_the_groups_freeze():
    named = rules_group(parse_rules(["robotistic", "egoistic"]))
    other = temperature_group(named.rules, 2.0)
    plan = SimpleNamespace(groups=(named, other))
    context = Context(plan, Scaling())
    fitted = Scaling("temperature", temperature=1.5)
    added = temperature_group(named.rules, 1.5)
    replaced = dataclasses.replace(other, note="replaced")
    context.apply(Provided(scaling=fitted, groups=(added,), replaced=(replaced,)))
    assert context.scaling is fitted
    assert [g.note for g in context.groups] == [named.note, "replaced", added.note]
    assert plan.groups == (named, other)  # the plan's own groups untouched
    context.freeze()
    assert isinstance(context.groups, tuple) and named_group(context.groups) is named


def _drawn_modules() -> set[str]:
    """The report modules whose functions an evaluation's results send to the figure workers:
    the first argument of each ``job(...)`` call in report/, traced to where it is defined."""
    import ast
    from pathlib import Path

    import costseg.report

    found = set()
    report = Path(costseg.report.__file__).parent
    for path in report.glob("*.py"):
        tree = ast.parse(path.read_text())
        imported = {a.asname or a.name: node.module for node in ast.walk(tree)
                    if isinstance(node, ast.ImportFrom) and node.module
                    for a in node.names}  # fmt: skip
        for node in ast.walk(tree):
            if isinstance(node, ast.Call) and getattr(node.func, "id", "") == "job" and node.args:
                name = getattr(node.args[0], "id", None)
                found.add(imported.get(name, f"costseg.report.{path.stem}"))
    assert found
    return found


def test_the_entries_declare_the_modules_of_every_figure_they_draw():
    import importlib

    from costseg import workers
    from costseg.evaluation.analyses import figure_modules

    declared = set(figure_modules(ANALYSES)) | set(workers.PRELOAD)
    for module in declared:
        importlib.import_module(module)
    assert _drawn_modules() <= declared
