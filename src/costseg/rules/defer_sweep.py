"""The defer-cost sweep of ``--defer_sweep START STOP STEP``: every rule of ``--cost`` with a
defer row of each cost START, START + STEP, …, STOP, decided as one group from the same
probabilities (docs/definitions.md §14: risk–coverage).

A rule's points form a path from its smallest defer cost (the most deferral) up; fixed-sequence
testing walks each path (``RuleGroup.paths``), and a tie under ``--target`` goes to the larger
defer cost (``RuleGroup.prefer``: the more coverage).

>>> defer_costs(0, 0.3, 0.1)
[0.0, 0.1, 0.2, 0.3]
>>> group = defer_group(["robotistic", "ml"], [0.0, 0.5])
>>> group.names
['robotistic@defer=0', 'robotistic@defer=0.5', 'ml@defer=0', 'ml@defer=0.5']
>>> group.columns[1], group.paths
({'matrix': 'robotistic', 'defer': 0.5}, ((0, 1), (2, 3)))
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence

from costseg.classes import CLASS_NAMES
from costseg.costs import cost_or_symmetric, with_defer
from costseg.rules.base import Rule, RuleGroup, needs_priors, needs_roi
from costseg.rules.named import NamedRules, parse_rules, rule_columns

DEFER_FAMILY = "defer"
"""The family label of the defer sweep (its own outputs: :mod:`costseg.report.risk_coverage`)."""

MAX_DEFER_POINTS = 101
"""The most defer costs of one sweep (each is one more decision per rule and image)."""


def defer_costs(start: float, stop: float, step: float) -> list[float]:
    """START, START + STEP, … up to STOP (included within rounding), each rounded to 12
    significant digits so that ``0.1 * 3`` is 0.3.

    Raises:
        ValueError: unless 0 <= START < STOP and STEP > 0, all finite, give 2 to
            :data:`MAX_DEFER_POINTS` costs.

    >>> defer_costs(0.5, 2, 0.5), defer_costs(0, 1, 0.4)
    ([0.5, 1.0, 1.5, 2.0], [0.0, 0.4, 0.8])
    """
    given = f"--defer_sweep {start:g} {stop:g} {step:g}"
    if not all(math.isfinite(v) for v in (start, stop, step)):
        raise ValueError(f"{given}: START, STOP and STEP must be finite numbers")
    if not (0 <= start < stop and step > 0):
        raise ValueError(f"{given}: expected 0 <= START < STOP and STEP > 0")
    span = (stop - start) / step
    whole = round(span)
    n = whole if math.isclose(span, whole, rel_tol=1e-9, abs_tol=1e-9) else math.floor(span)
    if n < 1:
        raise ValueError(f"{given} gives one defer cost: STEP must be at most STOP - START")
    if n + 1 > MAX_DEFER_POINTS:
        raise ValueError(
            f"{given} gives {n + 1} defer costs, at most {MAX_DEFER_POINTS}: take a larger STEP"
        )
    costs = [float(f"{start + i * step:.12g}") for i in range(n + 1)]
    if math.isclose(costs[-1], stop, rel_tol=1e-9):
        costs[-1] = float(stop)
    return costs


def defer_group(
    cost_names: Sequence[str], costs: Sequence[float], class_names: Sequence[str] = CLASS_NAMES
) -> RuleGroup:
    """The rules of ``cost_names`` (N x N, a regional stack of them, or ``ml``) with a defer row
    of each of ``costs``
    (ascending), rule after rule, as one group whose rules are the candidates of ``--target``.

    Raises:
        ValueError: costs not ascending from >= 0, a rule that has a defer row of its own, or
            one that :func:`~costseg.rules.named.parse_rules` refuses.
    """
    if not costs or any(a >= b for a, b in itertools.pairwise(costs)) or costs[0] < 0:
        raise ValueError(f"defer costs must be >= 0 and ascending, got {list(costs)}")
    bases = parse_rules(cost_names, class_names)
    for base in bases:
        if base.defers:
            raise ValueError(
                "--defer_sweep gives every class one defer cost, so it takes N x N cost "
                f"matrices; {base.name} has a defer row of its own"
            )
    n, rules, paths = len(class_names), [], []
    for base in bases:
        square = cost_or_symmetric(base.cost, n)
        paths.append(tuple(range(len(rules), len(rules) + len(costs))))
        rules += [Rule(base.name, with_defer(square, c), base.priors_alpha) for c in costs]
    return RuleGroup(
        DEFER_FAMILY,
        [f"{r.name}@defer={r.defer_cost:.12g}" for r in rules],
        NamedRules(tuple(rules)),
        [rule_columns(r, True) for r in rules],
        needs_priors=needs_priors(rules),
        needs_roi=needs_roi(rules),
        candidates=True,
        output="defer_sweep",
        rules=rules,
        paths=tuple(paths),
        prefer=tuple(float(c) for c in costs) * len(bases),
        note=f"{', '.join(b.name for b in bases)} with a defer cost of {costs[0]:g} to "
        f"{costs[-1]:g} ({len(costs)} points)",
    )
