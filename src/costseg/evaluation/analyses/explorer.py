"""``--explorer``: ``explorer.html``, the examples' probabilities decided again in the browser
under any mixture of the triangle's corners, next to the sweep's metrics (docs/definitions.md
§11)."""

from __future__ import annotations

from costseg.evaluation.analyses import Analysis
from costseg.evaluation.settings import ExplorerSettings
from costseg.report.explorer_points import ExplorerPage


class Explorer(Analysis):
    settings: ExplorerSettings

    def result(self) -> ExplorerPage:
        given = self.settings
        return ExplorerPage(given.vertices, given.vertex_scaling, given.defer)


ANALYSIS = Explorer
