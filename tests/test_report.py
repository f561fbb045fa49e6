"""Tests of costseg.report: atomic files, tables, figures, the triangle and TensorBoard helpers."""

from __future__ import annotations

import csv
import json
import math

import numpy as np
import pytest
import torch
from matplotlib.colors import to_rgba
from PIL import Image
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator
from torch.utils.tensorboard import SummaryWriter

from costseg.classes import CLASS_NAMES, PALETTE, ROI_CLASSES, class_indices, colorize
from costseg.report import files
from costseg.report.cost_matrix import plot_cost_matrix
from costseg.report.figures import (
    masks_side_by_side,
    plot_heatmap_grid,
    plot_masks,
)
from costseg.report.files import save_figure, write_csv, write_json, write_text
from costseg.report.priors import plot_priors, plot_roi_map
from costseg.report.tables import compare_with_paper, console_table, markdown_table, paper_table
from costseg.report.tensorboard import log_figures, log_masks, log_scalars, log_table
from costseg.report.ternary import plot_edge_tradeoffs, plot_ternary

NAN = float("nan")
H, W = 8, 16
RNG = np.random.default_rng(0)
IMAGE = RNG.integers(0, 256, (H, W, 3), dtype=np.uint8)
TARGET = np.zeros((H, W), dtype=np.int64)
TARGET[:2] = 255
TARGET[5:, 4:9] = 11  # person
PREDS = {"altruistic": np.full((H, W), 11), "egoistic": np.full((H, W), 2)}
HALF_GRID = np.array(  # barycentric grid of step 0.5 (6 points)
    [[1, 0, 0], [0.5, 0.5, 0], [0, 1, 0], [0.5, 0, 0.5], [0, 0.5, 0.5], [0, 0, 1]]
)


# ---------------------------------------------------------------- files


def test_write_text_creates_parents_and_leaves_no_temp(tmp_path):
    path = tmp_path / "a" / "b" / "result.md"
    write_text(path, "old")
    write_text(path, "x" * 100_000)
    assert path.read_text() == "x" * 100_000
    assert [p.name for p in path.parent.iterdir()] == ["result.md"]


def test_failed_write_keeps_old_file_and_removes_temp(tmp_path, monkeypatch):
    path = tmp_path / "r.json"
    write_json(path, {"v": 1})

    def crash(src, dst):
        raise OSError("disk full")

    monkeypatch.setattr(files.os, "replace", crash)
    with pytest.raises(OSError):
        write_json(path, {"v": 2})
    assert json.loads(path.read_text()) == {"v": 1}
    assert [p.name for p in tmp_path.iterdir()] == ["r.json"]


def test_json_nan_becomes_null_and_converts_numpy_torch(tmp_path):
    obj = {
        "recall": NAN,
        "inf": math.inf,
        "n": np.int64(3),
        "p": np.float32(0.5),
        "arr": np.array([0.25, np.nan]),
        "t": torch.tensor([[1, 2]]),
        "t0": torch.tensor(NAN),
        "rows": ({"fp": 2},),
    }
    text = write_json(tmp_path / "r.json", obj).read_text()
    assert "NaN" not in text and "Infinity" not in text
    assert json.loads(text) == {
        "recall": None,
        "inf": None,
        "n": 3,
        "p": 0.5,
        "arr": [0.25, None],
        "t": [[1, 2]],
        "t0": None,
        "rows": [{"fp": 2}],
    }
    with pytest.raises(ValueError, match="set"):
        write_json(tmp_path / "bad.json", {"s": {1, 2}})


def test_csv_round_trip(tmp_path):
    rows = [
        {"matrix": "ml", "precision": 0.5, "fp_segments": np.int64(3)},
        {"matrix": "egoistic", "precision": NAN, "miou": 0.25},
    ]
    with open(write_csv(tmp_path / "r.csv", rows), newline="") as f:
        back = list(csv.DictReader(f))
    assert list(back[0]) == ["matrix", "precision", "fp_segments", "miou"]
    assert back[0] == {"matrix": "ml", "precision": "0.5", "fp_segments": "3", "miou": ""}
    assert math.isnan(float(back[1]["precision"])) and float(back[1]["miou"]) == 0.25
    with pytest.raises(ValueError, match="at least one row"):
        write_csv(tmp_path / "empty.csv", [])


def test_save_figure_png_has_figsize_times_dpi_pixels(tmp_path):
    fig = plot_heatmap_grid({("ml", "person"): np.ones((H, W))})
    fig.set_size_inches(4, 3)
    path = save_figure(fig, tmp_path / "deep" / "f.png", dpi=50)
    assert Image.open(path).size == (200, 150)
    assert [p.name for p in path.parent.iterdir()] == ["f.png"]


# ---------------------------------------------------------------- tables


def test_markdown_table_percent_nan_and_missing():
    rows = [
        {"matrix": "altruistic", "precision": 0.4112, "recall": 0.9981, "fp_segments": 12},
        {"matrix": "egoistic", "precision": NAN, "recall": 0.0},
    ]
    table = markdown_table(rows, ["matrix", "precision", "recall", "fp_segments"], headers="mPRF")
    assert table.splitlines() == [
        "| m | P | R | F |",
        "|---|---|---|---|",
        "| altruistic | 41.12 | 99.81 | 12 |",
        "| egoistic | nan | 0.00 | — |",
    ]
    with pytest.raises(ValueError, match="expected 2 headers"):
        markdown_table(rows, ["matrix", "recall"], headers=["m"])


def test_console_table_aligns_columns():
    rows = [{"m": "ml", "recall": 0.5}, {"m": "altruistic", "recall": NAN}]
    lines = console_table(rows, ["m", "recall"]).splitlines()
    assert lines == [
        "m           recall",
        "----------  ------",
        "ml           50.00",
        "altruistic     nan",
    ]


def _row(matrix, cls, roi, precision, recall, **extra):
    return {
        "matrix": matrix,
        "class": cls,
        "roi": roi,
        "precision": precision,
        "recall": recall,
        **extra,
    }


def test_paper_table_groups_class_then_roi_then_matrix():
    rows = [
        _row("egoistic", "person", 1, 0.9, NAN, fp_segments=1),
        _row("egoistic", "building", 2, 0.1, 0.99, fp_segments=2),
        _row("robotistic", 11, "street", 0.8, 0.9, fp_segments=3),  # train id and RoI name
        _row("egoistic", "person", 2, 0.5, 0.5, fp_segments=4),
        _row("ml", "person", 1, 0.7, 0.7, fp_segments=5),
    ]
    assert paper_table(rows).splitlines() == [
        "| class | RoI | matrix | precision | recall | fp_segments "
        "| paper precision | paper recall |",
        "|---|---|---|---|---|---|---|---|",
        "| person | 1 street | egoistic | 90.00 | nan | 1 | 93.88 | 70.07 |",
        "|  |  | robotistic | 80.00 | 90.00 | 3 | 89.87 | 94.98 |",
        "|  |  | ml | 70.00 | 70.00 | 5 | — | — |",
        "|  | 2 sidewalk | egoistic | 50.00 | 50.00 | 4 | 95.07 | 54.81 |",
        "| building | 2 sidewalk | egoistic | 10.00 | 99.00 | 2 | 18.48 | 99.90 |",
    ]
    with pytest.raises(ValueError, match="roi"):
        paper_table([_row("ml", "person", 7, 0.5, 0.5)])
    with pytest.raises(ValueError, match="lacks recall"):
        paper_table([{"matrix": "ml", "class": "person", "roi": 1, "precision": 0.5}])


# docs/definitions.md §5, retyped here independently of tables.PAPER_TABLE.
SPEC_TABLE = """
altruistic person 1 41.12 99.81
robotistic person 1 89.87 94.98
egoistic person 1 93.88 70.07
altruistic person 2 39.42 99.86
robotistic person 2 88.36 93.93
egoistic person 2 95.07 54.81
altruistic building 1 22.56 93.65
robotistic building 1 80.99 94.94
egoistic building 1 15.15 99.93
altruistic building 2 24.94 95.22
robotistic building 2 87.76 94.58
egoistic building 2 18.48 99.90
"""


def test_compare_with_paper_carries_spec_numbers():
    measured = [_row("Robotistic", "building", 2, 0.5, NAN), _row("ml", "person", 1, 0.1, 0.1)]
    lines = compare_with_paper(measured).splitlines()
    assert lines[0] == (
        "| matrix | class | RoI | precision | recall | paper precision | paper recall |"
    )
    body = [[c.strip() for c in line.strip("|").split("|")] for line in lines[2:]]
    spec = [line.split() for line in SPEC_TABLE.strip().splitlines()]
    assert len(body) == len(spec) == 12
    for cells, (matrix, cls, roi, prec, rec) in zip(body, spec, strict=True):
        assert cells[:3] == [matrix, cls, f"{roi} {['', 'street', 'sidewalk'][int(roi)]}"]
        assert cells[5:] == [prec, rec]
        expected = (
            ["50.00", "nan"]
            if (matrix, cls, roi) == ("robotistic", "building", "2")
            else ["—", "—"]
        )
        assert cells[3:5] == expected


# ---------------------------------------------------------------- ternary


def test_ternary_weights_must_be_barycentric():
    with pytest.raises(ValueError, match="sum to 1"):
        plot_ternary([[0.5, 0.2, 0.2]], [1.0])
    with pytest.raises(ValueError, match=r"\(K, 3\)"):
        plot_ternary([[0.5, 0.5]], [1.0])


def test_plot_ternary_colours_high_blue_low_red_nan_grey():
    values = np.array([1.0, 0.5, 0.0, NAN, 0.9, 0.1])
    fig = plot_ternary(HALF_GRID, torch.tensor(values), note="vertices unscaled")
    cells = fig.axes[0].collections[0]
    cells.update_scalarmappable()
    colours = cells.get_facecolor()
    assert len(colours) == 6 and cells.get_clip_path() is not None
    np.testing.assert_allclose(colours[3], to_rgba("lightgrey"))
    assert colours[0][2] > colours[0][0] and colours[2][0] > colours[2][2]  # blue / red
    assert fig.texts[0].get_text() == "vertices unscaled"
    with pytest.raises(ValueError, match=r"shape \(6,\)"):
        plot_ternary(HALF_GRID, values[:5])


def test_plot_edge_tradeoffs_uses_points_of_each_edge():
    precision = np.array([0.1, 0.2, 0.3, 0.4, 0.5, 0.6])
    recall = 1 - precision
    fig = plot_edge_tradeoffs(HALF_GRID, precision, recall)
    expected = {  # edge → grid indices ordered from its first to its second vertex
        0: [0, 1, 2],  # R → A
        1: [2, 4, 5],  # A → E
        2: [5, 3, 0],  # E → R
    }
    for edge, idx in expected.items():
        prec_line, rec_line = fig.axes[edge].lines
        np.testing.assert_allclose(prec_line.get_xdata(), [0, 0.5, 1])
        np.testing.assert_allclose(prec_line.get_ydata(), 100 * precision[idx])
        np.testing.assert_allclose(rec_line.get_ydata(), 100 * recall[idx])
    assert fig.axes[0].get_title() == "Robotistic → Altruistic"


# ---------------------------------------------------------------- figures


def test_masks_side_by_side_matches_colorize():
    strip = masks_side_by_side(torch.from_numpy(IMAGE).permute(2, 0, 1), TARGET, PREDS)
    assert strip.shape == (H, 4 * W, 3) and strip.dtype == np.uint8
    np.testing.assert_array_equal(strip[:, :W], IMAGE)
    np.testing.assert_array_equal(strip[:, W : 2 * W], colorize(TARGET))
    np.testing.assert_array_equal(strip[:, 3 * W :], colorize(PREDS["egoistic"]))
    with pytest.raises(ValueError, match="target"):
        masks_side_by_side(IMAGE, TARGET[:4], PREDS)
    with pytest.raises(ValueError, match="uint8"):
        masks_side_by_side(IMAGE.astype(np.float32), TARGET, PREDS)


def test_plot_masks_panels_and_legend_of_present_classes():
    fig = plot_masks(IMAGE, torch.from_numpy(TARGET), PREDS)
    assert [ax.get_title() for ax in fig.axes] == ["image", "ground truth", *PREDS]
    legend = [t.get_text() for t in fig.legends[0].texts]
    assert legend == ["road", "building", "person", "ignore"]


def test_plot_cost_matrix_masks_zero_diagonal():
    cost = np.full((3, 3), 10.0)
    cost[0, 2] = 1000
    np.fill_diagonal(cost, 0)
    fig = plot_cost_matrix(torch.tensor(cost), ["a", "b", "c"], "egoistic")
    ax = fig.axes[0]
    shown = ax.images[0].get_array()
    np.testing.assert_array_equal(shown.mask, np.eye(3, dtype=bool))
    assert ax.images[0].norm.vmin == 10 and ax.images[0].norm.vmax == 1000
    # distinct indices as drawn: the hat is mathtext (a combining hat is lost in the font)
    assert (ax.get_xlabel(), ax.get_ylabel()) == (
        "true class $k$ (column)",
        r"predicted class $\hat{k}$ (row)",
    )
    assert [t.get_text() for t in ax.get_xticklabels()] == ["a", "b", "c"]
    with pytest.raises(ValueError, match=r"\(2, 2\) cost matrix"):
        plot_cost_matrix(cost, ["a", "b"])


def test_heatmap_grid_rows_classes_columns_rules_shared_scale():
    maps = {
        ("altruistic", "person"): np.full((H, W), 2.0),
        ("egoistic", "person"): np.eye(H, W),
        ("egoistic", "building"): np.zeros((H, W)),
    }
    fig = plot_heatmap_grid(maps, kind="FN")
    panels = fig.axes[:4]
    assert [ax.get_title() for ax in panels[:2]] == ["altruistic", "egoistic"]
    assert [panels[0].get_ylabel(), panels[2].get_ylabel()] == ["person", "building"]
    assert {ax.images[0].get_clim() for ax in panels if ax.images} == {(0.0, 2.0)}
    assert panels[2].texts[0].get_text() == "not computed"
    with pytest.raises(ValueError, match="at least one"):
        plot_heatmap_grid({})


def test_roi_map_and_priors_validate_inputs():
    with pytest.raises(ValueError, match=r"RoI ids 0\.\.4"):
        plot_roi_map(np.full((H, W), 5))
    with pytest.raises(ValueError, match=r"\(19, H, W\) priors"):
        plot_priors(np.ones((3, H, W)))
    with pytest.raises(ValueError, match="unknown class"):
        plot_priors(np.ones((19, H, W)), classes=("pedestrian",))


ROI = np.repeat(np.arange(1, 5), H * W // 4).reshape(H, W)
PRIORS = np.full((len(CLASS_NAMES), H, W), 1 / len(CLASS_NAMES))
FIGURES = {
    "masks": lambda: plot_masks(IMAGE, TARGET, PREDS),
    "grid": lambda: plot_heatmap_grid({("ml", "person"): np.ones((H, W))}),
    "cost": lambda: plot_cost_matrix(np.ones((19, 19)) - np.eye(19), CLASS_NAMES, "robotistic"),
    "roi": lambda: plot_roi_map(ROI),
    "priors": lambda: plot_priors(torch.from_numpy(PRIORS)),
    "ternary": lambda: plot_ternary(HALF_GRID, np.linspace(0, 1, 6), note="unscaled"),
    "edges": lambda: plot_edge_tradeoffs(HALF_GRID, np.ones(6), np.zeros(6)),
}


@pytest.mark.parametrize("name", FIGURES)
def test_every_figure_saves_png_of_figsize_times_dpi(tmp_path, name):
    fig = FIGURES[name]()
    dpi = 30
    path = save_figure(fig, tmp_path / f"{name}.png", dpi=dpi)
    with Image.open(path) as img:
        assert img.format == "PNG"
        expected = tuple(round(v) for v in fig.get_size_inches() * dpi)
        assert img.size == expected


def _cell_colours(fig, png, ax, shape):
    """(h, w, 3) RGB of the saved ``png`` at the centre of each cell of ``ax``'s image."""
    with Image.open(png) as img:
        rgb = np.asarray(img.convert("RGB"))
    rows, cols = np.mgrid[: shape[0], : shape[1]]
    xy = (ax.transData + fig.transFigure.inverted()).transform(np.c_[cols.ravel(), rows.ravel()])
    x = (xy[:, 0] * rgb.shape[1]).astype(int)
    y = ((1 - xy[:, 1]) * rgb.shape[0]).astype(int)  # figure y runs up, PNG rows down
    return rgb[y, x].reshape(*shape, 3)


BLACK = np.zeros(3, np.uint8)
PANEL_COLOURS = {  # title → (H, W, 3): the image, or the palette colour of each class
    "masks": {
        "image": IMAGE,
        "ground truth": np.where((TARGET == 255)[..., None], BLACK, PALETTE[TARGET % 255]),
        **{rule: PALETTE[pred] for rule, pred in PREDS.items()},
    },
    "roi": {"regions of interest": PALETTE[class_indices(ROI_CLASSES)][ROI - 1]},
}


@pytest.mark.parametrize("name", PANEL_COLOURS)
@pytest.mark.parametrize("dpi", [30, 50])
def test_saved_png_shows_each_pixel_in_its_image_or_palette_colour(tmp_path, name, dpi):
    fig = FIGURES[name]()
    png = save_figure(fig, tmp_path / f"{name}.png", dpi=dpi)
    panels = [ax for ax in fig.axes if ax.images]
    assert [ax.get_title() for ax in panels] == list(PANEL_COLOURS[name])
    for ax, expected in zip(panels, PANEL_COLOURS[name].values(), strict=True):
        np.testing.assert_array_equal(_cell_colours(fig, png, ax, (H, W)), expected, ax.get_title())


# ---------------------------------------------------------------- tensorboard


def test_tensorboard_helpers_write_readable_events(tmp_path):
    with SummaryWriter(tmp_path) as writer:
        log_table(writer, "eval/table", "| a |\n|---|\n| 1 |")
        log_figures(writer, {"eval/ternary": FIGURES["ternary"]()}, step=3)
        skipped = log_scalars(writer, {"eval/recall": 0.25, "eval/precision": NAN}, step=3)
        log_masks(writer, "eval/masks", IMAGE, TARGET, PREDS)
    assert skipped == ["eval/precision"]
    acc = EventAccumulator(str(tmp_path), size_guidance={"images": 0, "tensors": 0}).Reload()
    tags = acc.Tags()
    assert set(tags["images"]) == {"eval/ternary", "eval/masks"}
    assert tags["scalars"] == ["eval/recall"]
    assert [(e.step, e.value) for e in acc.Scalars("eval/recall")] == [(3, 0.25)]
    text = acc.Tensors("eval/table/text_summary")[0].tensor_proto.string_val[0]
    assert text.decode() == "| a |\n|---|\n| 1 |"
    masks = acc.Images("eval/masks")[0]
    assert (masks.width, masks.height) == (4 * W, H)
