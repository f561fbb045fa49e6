"""Which outputs each rule family writes beyond its rows in the shared files: one table.

A family (:mod:`costseg.rules`) whose groups have an ``output`` gets :func:`sweep_outputs`
(``<output>.csv`` / ``.json``, triangles or curves, TensorBoard curves) unless it has an entry
here; a new family with outputs of its own is its module in ``rules/`` and one entry.
"""

from __future__ import annotations

from collections.abc import Callable

from costseg.meta.fusion import FUSED_FAMILY
from costseg.report.results import EvalResults, GroupResult
from costseg.report.risk_coverage import risk_coverage_outputs
from costseg.report.sections import Section
from costseg.report.segments import fusion_outputs
from costseg.report.sweep import sweep_outputs
from costseg.report.temperatures import temperature_outputs
from costseg.rules import DEFER_FAMILY, TEMPERATURE_FAMILY

FAMILY_OUTPUTS: dict[str, Callable[[EvalResults, list[GroupResult]], Section]] = {
    DEFER_FAMILY: risk_coverage_outputs,
    TEMPERATURE_FAMILY: temperature_outputs,
    FUSED_FAMILY: fusion_outputs,
}


def family_sections(results: EvalResults) -> list[Section]:
    """The outputs of every family of the evaluation's rule groups, in the groups' order."""
    families: dict[str, list[GroupResult]] = {}
    for result in results.groups:
        families.setdefault(result.group.family, []).append(result)
    return [FAMILY_OUTPUTS.get(f, sweep_outputs)(results, mine) for f, mine in families.items()]
