"""``--target`` / ``--maximize``: the point of the sweep that meets the target on the reported
images with the best objective (``best.json``, and ``best_cost.yaml`` for a cost matrix); the
explorer marks it. With ``--guarantee`` the certified choice is :mod:`.guarantee`'s."""

from __future__ import annotations

from costseg.evaluation.analyses import Analysis
from costseg.evaluation.settings import SweepChoice
from costseg.report.sweep import SweepPoint


class Choice(Analysis):
    settings: SweepChoice

    def result(self) -> SweepPoint:
        return SweepPoint(self.settings.target, self.settings.maximize)


ANALYSIS = Choice
