"""Every figure an evaluation draws shows all its text at the size it is saved, and says what it
shows: each figure of two tiny evaluations (every option that adds figures) is drawn in this
process, as the figure workers draw it, and each text's window extent is compared with the
figure's bounding box."""

from __future__ import annotations

import matplotlib
import pytest
from matplotlib.figure import Figure
from matplotlib.text import Text

from costseg.checkpoints import find_checkpoint
from costseg.cli import evaluate_main
from costseg.report.drawing import figure_path
from costseg.report.figures import plot_heatmap_grid
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
                    CLIPPED.extend(f"{tag}: {what}" for what in clipped_texts(fig))
                    TITLES[tag] = " ".join(_titles(fig))
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


CLIPPED: list[str] = []
TITLES: dict[str, str] = {}
RUNS = [
    ["--cost", "robotistic", "ml", "--calibrate", "temperature",
     "--temperature_sweep", "--sweep", "0.5", "--alpha_sweep", "0.5",
     "--defer_sweep", "0.2", "0.6", "0.2", "--meta", "--meta_split", "train",
     "--meta_images", "6", "--fuse", "ml", "--fuse_tau", "0", "1"],
    ["--cost", "robotistic", "--anomalies", "--shift", "fog:2"],
]  # fmt: skip


@pytest.fixture(scope="module")
def drawn(tiny_run, tmp_path_factory):
    """The tags of the figures of :data:`RUNS`, with their texts checked."""
    ckpt = str(find_checkpoint(None, runs_dir=tiny_run[2]))
    CLIPPED.clear(), TITLES.clear()
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr("costseg.report.early_figures.Drawing", InProcessDrawing)
        for i, args in enumerate(RUNS):
            out = tmp_path_factory.mktemp(f"figures_{i}")
            common = ["--ckpt_path", ckpt, "--output_dir", str(out), "--classes", "person"]
            evaluate_main([*common, *args, "--num_examples", "1", "--no-progress"])
    return dict(TITLES)


def test_no_text_of_any_figure_is_clipped(drawn):
    kinds = {tag.split("_")[0].split("/")[0] for tag in drawn}
    every = {"masks", "fp", "fn", "missed", "cost", "roi", "reliability", "temperature",
             "ternary", "edges", "alpha", "risk", "meta", "fusion", "anomaly"}  # fmt: skip
    assert every <= kinds, every - kinds
    assert not CLIPPED, "\n".join(CLIPPED)


def test_every_figure_says_what_it_shows(drawn):
    assert "person" in drawn["edges_person_roi1"] and "RoI 1" in drawn["edges_person_roi1"]
    assert "robotistic" in drawn["meta/segments_0_robotistic"]
    assert "gradient_boosting" in drawn["meta/segments_0_robotistic"]
    for tag in ("masks_0", "fp_segments", "missed_instances", "anomaly_maps_0"):
        assert "costseg:" in drawn[tag] and "version_" in drawn[tag], tag  # the network
    assert "fog:2" in drawn["anomaly_maps_0"] and "fog:2" in drawn["masks_0"]


def test_a_tall_colour_bar_label_fits_one_row_of_panels():
    """missed_instances.png: one row of wide panels under a long title."""
    maps = {(rule, "person"): [[0.0, 0.2]] * 2 for rule in ("robotistic", "altruistic")}
    fig = plot_heatmap_grid(maps, "missed instances")
    render(fig)
    assert clipped_texts(fig) == []
    fig.colorbar(fig.axes[0].images[0], ax=fig.axes[:2], label="x" * 80)  # a label too long
    render(fig)
    assert any("x" * 80 in what for what in clipped_texts(fig))
