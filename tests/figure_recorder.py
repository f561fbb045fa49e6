"""A stand-in for the figure workers in tests that do not look at figures: each job is checked
to pickle without a tensor, as the workers need, and recorded, never drawn (drawing is most of
a small evaluation's time). A test that reads figures is marked ``figures`` and draws them."""

from __future__ import annotations

from pathlib import Path

from costseg.report.drawing import payload


class RecordedDrawing:
    """:class:`costseg.report.drawing.Drawing` without workers: ``jobs`` holds what was
    submitted; :meth:`finish` reports no figure drawn."""

    def __init__(self, folder: Path, processes: int) -> None:
        self.folder, self.prefixes, self.jobs = folder, [], []

    def submit(self, prefix: str, drawn_job) -> None:
        payload(drawn_job)  # as the workers take it: pickled, without a tensor
        self.prefixes.append(prefix)
        self.jobs.append(drawn_job)

    def finish(self) -> list[tuple[str, list]]:
        return [(prefix, []) for prefix in self.prefixes]

    def cancel(self, timeout: float = 0) -> None:
        pass
