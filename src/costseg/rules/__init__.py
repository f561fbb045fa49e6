"""Decision rules and rule groups: what ``--cost``, ``--sweep``, ``--alpha_sweep``,
``--temperature_sweep`` and ``--defer_sweep`` decide (docs/definitions.md §1, §2, §6, §14).

One module per family, each building a :class:`~costseg.rules.base.RuleGroup` (K rules decided
together from one softmax: ``probs → (B, K, H, W)``): :mod:`.named` (the rules of ``--cost``),
:mod:`.triangle` (the value-space grid), :mod:`.alpha` (the prior-adapted path),
:mod:`.temperatures` and :mod:`.defer_sweep` (the named rules at many defer costs). The
evaluation loop and validation feed every group's label maps to the metrics; the reports write
any group from what it carries.
"""

from costseg.rules.alpha import alpha_grid, alpha_group
from costseg.rules.base import (
    DEFER_COLUMN,
    Rule,
    RuleGroup,
    adapted_priors,
    masked_groups,
    named_group,
    plain_rules,
    require_priors,
    require_roi,
)
from costseg.rules.defer_sweep import DEFER_FAMILY, defer_costs, defer_group
from costseg.rules.named import RULE_NAMES, apply_rules, parse_rules, rules_group
from costseg.rules.temperatures import TEMPERATURE_FAMILY, TEMPERATURES, temperature_group
from costseg.rules.triangle import grid_group, point_name, vertex_matrices

__all__ = [
    "DEFER_COLUMN",
    "DEFER_FAMILY",
    "RULE_NAMES",
    "TEMPERATURES",
    "TEMPERATURE_FAMILY",
    "Rule",
    "RuleGroup",
    "adapted_priors",
    "alpha_grid",
    "alpha_group",
    "apply_rules",
    "defer_costs",
    "defer_group",
    "grid_group",
    "masked_groups",
    "named_group",
    "parse_rules",
    "plain_rules",
    "point_name",
    "require_priors",
    "require_roi",
    "rules_group",
    "temperature_group",
    "vertex_matrices",
]
