"""What one analysis adds to the outputs every evaluation shares: keys of results.json, a
section of table.md, lines on the terminal, TensorBoard text tables and curves, and figures as
undrawn jobs. Each analysis writes its own files itself; :func:`merge` joins the sections in the
analyses' order."""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from costseg.report.drawing import Job

if TYPE_CHECKING:
    from torch.utils.tensorboard import SummaryWriter

    from costseg.report.results import EvalResults

Curve = tuple[str, str | None, list[int], list[float]]
"""A TensorBoard curve: tag, run (a class's own run, or None), steps, values."""


@dataclass
class Section:
    """One analysis's share of the shared outputs.

    Attributes:
        json: keys of results.json.
        table: a section of table.md ("" for none), with the blank lines that set it apart
            from the one before.
        console: lines for the terminal, printed in order.
        tables: TensorBoard text tables, tag → Markdown.
        curves: TensorBoard scalars along steps.
        jobs: figures, undrawn, as ``(TensorBoard prefix, job)``.
        logs: anything else for TensorBoard, each called with the evaluation's writer.
    """

    json: dict = field(default_factory=dict)
    table: str = ""
    console: list[str] = field(default_factory=list)
    tables: dict[str, str] = field(default_factory=dict)
    curves: list[Curve] = field(default_factory=list)
    jobs: list[tuple[str, Job]] = field(default_factory=list)
    logs: list[Callable[[SummaryWriter], None]] = field(default_factory=list)


def merge(sections: Iterable[Section]) -> Section:
    """The sections joined: their JSON keys, tables, lines, curves and jobs, in order."""
    out = Section()
    for s in sections:
        out.json |= s.json
        out.table += s.table
        out.console += s.console
        out.tables |= s.tables
        out.curves += s.curves
        out.jobs += s.jobs
        out.logs += s.logs
    return out


class Result:
    """What one analysis found (:mod:`costseg.evaluation.analyses`); it writes its own files."""

    def write(self, results: EvalResults) -> Section:
        """Write this result's files into ``results.output_dir``; return its share of the
        shared outputs."""
        raise NotImplementedError
