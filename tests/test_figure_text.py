"""Every figure an evaluation draws shows all its text at the size it is saved, and says what it
shows: each figure of the tiny evaluations of ``every_output`` (every option that adds figures)
is drawn in this process, as the figure workers draw it, and each text's window extent is
compared with the figure's bounding box (figure_text.py)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from figure_text import clipped_texts

from costseg.classes import CLASS_NAMES, ROI_NAMES
from costseg.report.figures import heatmap_grid_figures, plot_heatmap_grid
from costseg.report.files import render
from costseg.report.priors import plot_priors, plot_roi_map


@pytest.fixture(scope="module")
def drawn(every_figure) -> dict[str, str]:
    """tag → the titles of every figure the evaluations of ``every_output`` drew."""
    return every_figure["titles"]


def test_no_text_of_any_figure_is_clipped(drawn, every_figure):
    kinds = {tag.split("_")[0].split("/")[0] for tag in drawn}
    every = {"masks", "fp", "fn", "missed", "cost", "roi", "reliability", "temperature",
             "ternary", "edges", "alpha", "risk", "meta", "fusion", "anomaly"}  # fmt: skip
    assert every <= kinds, every - kinds
    assert not every_figure["clipped"], "\n".join(every_figure["clipped"])


def test_every_figure_says_what_it_shows(drawn):
    assert "person" in drawn["edges_person_roi1"] and "RoI 1 (street)" in drawn["edges_person_roi1"]
    ternaries = [tag for tag in drawn if tag.startswith("ternary_person_roi")]
    assert ternaries
    for tag in ternaries:  # the RoI named as the edge plots name it
        roi = int(tag.split("_roi")[1][0])
        assert f"RoI {roi} ({ROI_NAMES[roi]})" in drawn[tag], (tag, drawn[tag])
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


def test_a_grid_drawn_again_with_a_finer_colour_scale_keeps_its_label():
    """FP and FN segments, then missed instances on the same grid: ticks of "0.175" after "0.5"
    are wider, and the colour bar's label must still fit."""
    rng = np.random.default_rng(0)
    shares = {(r, c): rng.random((128, 256)) for r in ("robotistic", "egoistic") for c in
              ("person", "car")}  # fmt: skip
    grids = [(kind, {k: v * top for k, v in shares.items()}, kind)
             for kind, top in (("FP", 0.5), ("FN", 0.5), ("missed instances", 0.21))]  # fmt: skip
    for _, fig in heatmap_grid_figures(grids, "costseg:toy/version_0"):
        render(fig)
        assert clipped_texts(fig) == []


def test_the_training_run_s_figures_show_all_their_text():
    """priors.png and roi_map.png of train.py, at the toy world's size."""
    priors = torch.full((len(CLASS_NAMES), 128, 256), 1 / len(CLASS_NAMES))
    roi = np.repeat(np.arange(1, 5), 128 * 256 // 4).reshape(128, 256)
    for fig in (plot_priors(priors), plot_roi_map(roi)):
        render(fig)
        assert clipped_texts(fig) == []
