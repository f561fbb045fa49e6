"""Figures of the pixel-wise priors and the RoI map (docs/definitions.md §3)."""

from __future__ import annotations

from collections.abc import Iterator, Sequence

import numpy as np
from matplotlib.colors import ListedColormap
from matplotlib.figure import Figure
from matplotlib.patches import Patch

from costseg.classes import CLASS_NAMES, PALETTE, ROI_NAMES, class_index
from costseg.report.figures import PANEL, ArrayLike, as_numpy

_ROI_COLOURS = np.vstack([[0, 0, 0], PALETTE[[0, 1, 2, 10]]]) / 255  # road, sidewalk, building, sky


def plot_roi_map(roi: ArrayLike) -> Figure:
    """The RoI map (1 street, 2 sidewalk, 3 building, 4 sky) in Cityscapes colours with a legend.

    Args:
        roi: (H, W) integer RoI ids in 0..4 (0, black: not assigned to any RoI).

    >>> plot_roi_map(np.array([[1, 2], [3, 4]])).axes[0].get_legend().texts[0].get_text()
    '1 street'
    """
    ids = as_numpy(roi)
    if ids.ndim != 2 or not np.isin(ids, range(len(ROI_NAMES))).all():
        raise ValueError(
            f"expected an (H, W) map of RoI ids 0..4, got shape {ids.shape}, "
            f"values {np.unique(ids)[:8].tolist()}"
        )
    height, width = ids.shape
    fig = Figure(figsize=(6.0, 6.0 * height / width + 0.8), layout="constrained")
    ax = fig.subplots()
    ax.imshow(ids, cmap=ListedColormap(_ROI_COLOURS), vmin=-0.5, vmax=4.5, interpolation="nearest")
    ax.set_axis_off()
    ax.set_title("regions of interest")
    # Id 0 means "whole image" in results but "no RoI" in a map; list it only if it occurs.
    labels = {i: f"{i} {ROI_NAMES[i]}" for i in range(1, len(ROI_NAMES))}
    labels = {0: "0 none"} | labels if (ids == 0).any() else labels
    handles = [Patch(facecolor=_ROI_COLOURS[i], label=text) for i, text in labels.items()]
    ax.legend(
        handles=handles,
        loc="upper center",
        bbox_to_anchor=(0.5, 0.0),
        ncols=len(handles),
        fontsize="small",
        frameon=False,
    )
    return fig


def roi_map_figures(roi: ArrayLike) -> Iterator[tuple[str, Figure]]:
    """``("roi_map", plot_roi_map(roi))``, as a drawing job."""
    yield "roi_map", plot_roi_map(roi)


def plot_priors(
    priors: ArrayLike,
    class_names: Sequence[str] = CLASS_NAMES,
    classes: Sequence[str] = ("road", "sidewalk", "building", "sky", "person", "car"),
) -> Figure:
    """Small multiples of pixel-wise priors π(k | location), one panel per class.

    Each panel has its own colour bar from 0 to its maximum, so that rare classes (person)
    stay visible next to frequent ones (road, sky).

    Args:
        priors: (N, H, W) per-location class frequencies.
        class_names: the N class names.
        classes: the classes to show, by name.

    >>> len(plot_priors(np.full((19, 4, 8), 1 / 19), classes=("road", "sky")).axes)  # + 2 bars
    4
    """
    pi = as_numpy(priors)
    if pi.ndim != 3 or pi.shape[0] != len(class_names):
        raise ValueError(f"expected ({len(class_names)}, H, W) priors, got shape {pi.shape}")
    index = [class_index(name, class_names) for name in classes]
    ncols = min(3, len(index))
    nrows = -(-len(index) // ncols)
    height, width = pi.shape[1:]
    size = ((PANEL + 0.8) * ncols, (PANEL * height / width + 0.4) * nrows)
    fig = Figure(figsize=size, layout="constrained")
    axes = fig.subplots(nrows, ncols, squeeze=False).ravel()
    for ax in axes:
        ax.set_axis_off()
    for ax, k in zip(axes, index, strict=False):
        im = ax.imshow(pi[k], cmap="viridis", vmin=0, interpolation="bilinear")
        ax.set_title(f"π({class_names[k]})")
        fig.colorbar(im, ax=ax, shrink=0.8)
    return fig
