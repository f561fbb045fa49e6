"""Figures drawn in the test process as the figure workers draw them, each text checked against
the figure's bounding box (:func:`clipped_texts`) and its titles kept: for tests of every figure
an evaluation draws (``InProcessDrawing`` stands in for :class:`costseg.report.drawing.Drawing`)."""

from __future__ import annotations

from typing import ClassVar

import matplotlib
from matplotlib.figure import Figure
from matplotlib.text import Text

from costseg.report.drawing import figure_path
from costseg.report.files import render, write_png

SLACK = 1.0  # pixels: antialiasing may touch the border


def clipped_texts(fig: Figure) -> list[str]:
    """The texts of a drawn ``fig`` that reach beyond its bounding box: every text artist,
    and each axis's tick labels and label together (those of ticks outside the view limits
    are never drawn, :meth:`~matplotlib.axis.Axis.get_tightbbox` leaves them out)."""
    renderer, box = fig.canvas.get_renderer(), fig.bbox
    ticks = {
        id(label)
        for ax in fig.axes
        for axis in (ax.xaxis, ax.yaxis)
        for label in axis.get_ticklabels(which="both")
    }
    boxes = []
    for text in fig.findobj(Text):
        shown = text.get_visible() and (text.axes is None or text.axes.get_visible())
        if shown and text.get_text().strip() and id(text) not in ticks:
            boxes.append((repr(text.get_text()), text.get_window_extent(renderer)))
    for ax in fig.axes:
        for name, axis in (("x", ax.xaxis), ("y", ax.yaxis)):
            drawn = ax.get_visible() and ax.axison and axis.get_visible()
            extent = axis.get_tightbbox(renderer) if drawn else None
            if extent is not None:
                boxes.append((f"{name} axis of {ax.get_title()!r}", extent))
    return [
        what
        for what, e in boxes
        if e.x0 < box.x0 - SLACK
        or e.y0 < box.y0 - SLACK
        or e.x1 > box.x1 + SLACK
        or e.y1 > box.y1 + SLACK
    ]


class InProcessDrawing:
    """:class:`costseg.report.drawing.Drawing` in this process: each figure drawn as a worker
    draws it, then its texts checked (:func:`clipped_texts`) and its title kept."""

    clipped: ClassVar[list[str]] = []  # "<tag>: <text>" of every clipped text, over all instances
    titles: ClassVar[dict[str, str]] = {}  # tag → the figure's titles, over all instances

    def __init__(self, folder, processes: int) -> None:
        self.folder, self.jobs = folder, []

    def submit(self, prefix: str, drawn_job) -> None:
        self.jobs.append((prefix, drawn_job))

    def finish(self) -> list:
        done = []
        with matplotlib.rc_context({"axes.titley": 1.0}):  # as the workers draw
            for prefix, drawn_job in self.jobs:
                drawn = []
                for tag, fig in drawn_job():
                    image = render(fig)
                    self.clipped.extend(f"{tag}: {what}" for what in clipped_texts(fig))
                    self.titles[tag] = " ".join(_titles(fig))
                    write_png(figure_path(self.folder, tag), image)
                    drawn.append((tag, image.shape))
                done.append((prefix, drawn))
        return done

    def cancel(self, timeout: float = 0) -> None:
        pass


def _titles(fig: Figure) -> list[str]:
    """The figure's title, its axes' titles and its bottom line."""
    texts = [fig._suptitle, fig._supxlabel, *(ax.title for ax in fig.axes)]
    return [t.get_text() for t in texts if t is not None]
