"""The temperature sweep: the named rules on ``softmax(z / T)`` for several T, one group per T
(docs/definitions.md §6: cost rules move with T, argmax does not).

>>> from costseg.rules.named import parse_rules
>>> temperature_group(parse_rules(["egoistic"]), 0.5).names
['egoistic@T=0.50']
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace

from costseg.rules.base import Rule, RuleGroup
from costseg.rules.named import rule_columns, rules_group

TEMPERATURES = (0.5, 0.75, 1.0, 1.25, 1.5, 1.75, 2.0)
TEMPERATURE_FAMILY = "temperature"


def temperature_group(rules: Sequence[Rule], temperature: float) -> RuleGroup:
    """The named rules, decided on ``softmax(z / T)`` of the logits, as one group."""
    defer = any(r.defers for r in rules)
    return replace(
        rules_group(rules),
        family=TEMPERATURE_FAMILY,
        names=[f"{r.name}@T={temperature:.2f}" for r in rules],
        columns=[rule_columns(r, defer) | {"temperature": temperature} for r in rules],
        is_named=False,
        heatmaps=False,
        temperature=temperature,
    )
