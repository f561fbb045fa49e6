"""The value-space triangle (docs/definitions.md §2): heatmaps over barycentric weights and
trade-offs per edge.

A grid point ``(α, β, γ)`` (``α + β + γ = 1``) stands for the mixture ``α C_0 + β C_1 + γ C_2`` of
three vertex matrices, by default ``C_R, C_A, C_E``. Mixing is not scale invariant, so every
figure carries a ``note`` line that should say how the vertices were scaled.

A sweep draws many metrics over one grid: :func:`ternary_figures` and
:func:`edge_tradeoff_figures` build the figure once and redraw it with each metric's values.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator, Sequence

import numpy as np
import torch
from matplotlib import colormaps
from matplotlib.axes import Axes
from matplotlib.collections import PolyCollection
from matplotlib.colors import Colormap, Normalize
from matplotlib.figure import Figure
from matplotlib.patches import Polygon

from costseg.report.figures import freeze_layout
from costseg.report.files import redraw_only

ArrayLike = np.ndarray | torch.Tensor
LABELS = ("Robotistic", "Altruistic", "Egoistic")
CORNERS = np.array([[0.0, 0.0], [1.0, 0.0], [0.5, np.sqrt(3) / 2]])
"""(3, 2) cartesian corners of vertex 0 (bottom left), 1 (bottom right) and 2 (top)."""
EDGES = ((0, 1), (1, 2), (2, 0))


def _weights(weights: ArrayLike) -> np.ndarray:
    w = np.asarray(weights.detach().cpu() if isinstance(weights, torch.Tensor) else weights)
    w = w.astype(np.float64)
    if w.ndim != 2 or w.shape[1] != 3 or len(w) == 0:
        raise ValueError(f"expected (K, 3) barycentric weights, got shape {w.shape}")
    if not (np.isfinite(w).all() and (w >= -1e-9).all() and np.allclose(w.sum(1), 1, atol=1e-6)):
        raise ValueError(
            "expected non-negative weights whose rows sum to 1, got rows like "
            f"{w[np.argmax(np.abs(w.sum(1) - 1))].tolist()}"
        )
    return w


def _values(values: ArrayLike, k: int, name: str) -> np.ndarray:
    v = np.asarray(values.detach().cpu() if isinstance(values, torch.Tensor) else values, float)
    if v.shape != (k,):
        raise ValueError(f"expected {name} of shape ({k},), one per grid point, got {v.shape}")
    return v


def _cells(xy: np.ndarray) -> np.ndarray:
    # Each point gets the hexagon of the triangular lattice around it (its Voronoi cell);
    # the spacing is the nearest-neighbour distance, i.e. the grid step h on the unit triangle.
    from scipy.spatial import cKDTree  # imported only for a sweep's figures

    spacing = cKDTree(xy).query(xy, k=2)[0][:, 1].min() if len(xy) > 1 else 1.0
    angles = np.deg2rad(30 + 60 * np.arange(6))
    hexagon = spacing / np.sqrt(3) * np.stack([np.cos(angles), np.sin(angles)], axis=1)
    return xy[:, None, :] + hexagon[None]


def plot_ternary(
    weights: ArrayLike,
    values: ArrayLike,
    vertex_labels: Sequence[str] = LABELS,
    title: str = "",
    cbar_label: str = "",
    cmap: str = "RdYlBu",
    vmin: float = 0.0,
    vmax: float = 1.0,
    note: str = "",
) -> Figure:
    """Heatmap of one metric over the triangle, like the paper's "recall of person pixels".

    Each grid point is drawn as its hexagonal cell, clipped to the triangle. With the default
    ``RdYlBu`` colour map high values are blue and low ones red; NaN cells are grey.

    Args:
        weights: (K, 3) barycentric weights of the grid points.
        values: (K,) the metric at each point (NaN where undefined).
        vertex_labels: names of the three vertices, in the weights' column order.
        title: figure title.
        cbar_label: colour bar label, e.g. "recall (person, RoI 1)".
        cmap: matplotlib colour map name.
        vmin: bottom of the colour scale.
        vmax: top of the colour scale.
        note: small text line under the triangle; state the vertex scaling here.

    >>> w = np.array([[1, 0, 0], [0, 1, 0], [0, 0, 1], [0.5, 0.5, 0]])
    >>> fig = plot_ternary(w, [0.9, 0.1, np.nan, 0.5], note="vertices unscaled")
    >>> fig.axes[0].collections[0].get_array().mask.tolist()
    [False, False, True, False]
    """
    panels = [("", values, title, cbar_label)]
    return next(ternary_figures(weights, panels, vertex_labels, cmap, vmin, vmax, note))[1]


def ternary_figures(
    weights: ArrayLike,
    panels: Iterable[tuple[str, ArrayLike, str, str]],
    vertex_labels: Sequence[str] = LABELS,
    cmap: str = "RdYlBu",
    vmin: float = 0.0,
    vmax: float = 1.0,
    note: str = "",
) -> Iterator[tuple[str, Figure]]:
    """:func:`plot_ternary` of each ``(tag, values, title, cbar_label)``, as ``(tag, figure)``.

    All share one figure, redrawn for each: draw it before taking the next.

    >>> w = np.array([[1, 0, 0], [0, 1, 0], [0, 0, 1]])
    >>> panels = [("p", [0.1, 0.2, 0.3], "precision", ""), ("r", [0.4, 0.5, 0.6], "recall", "")]
    >>> [fig.axes[0].get_title() for _, fig in ternary_figures(w, panels)]
    ['precision', 'recall']
    """
    w = _weights(weights)
    fig = None
    for tag, values, title, cbar_label in panels:
        v = np.ma.masked_invalid(_values(values, len(w), "values"))
        first = fig is None
        if first:
            fig = Figure(figsize=(5.5, 4.5), layout="constrained")
            ax = fig.subplots()
            cells = _triangle(ax, w, v, vertex_labels, colormaps[cmap], Normalize(vmin, vmax))
            bar = fig.colorbar(cells, ax=ax, shrink=0.8)
            fig.supxlabel(note, fontsize="small", wrap=True)
        cells.set_array(v)
        ax.set_title(title, y=1.0)  # a fixed height: no tick lifts it (axes off)
        bar.set_label(cbar_label)
        if first:
            redraw_only(freeze_layout(fig), [cells, ax.title, bar.ax.yaxis.label])
        yield tag, fig


def _triangle(
    ax: Axes,
    w: np.ndarray,
    v: np.ma.MaskedArray,
    vertex_labels: Sequence[str],
    cmap: Colormap,
    norm: Normalize,
) -> PolyCollection:
    """Draw the outline, the cells of the grid points and the vertex labels into ``ax``."""
    outline = Polygon(CORNERS, closed=True, fill=False, edgecolor="black", linewidth=1.0)
    ax.add_patch(outline)
    cells = PolyCollection(
        _cells(w @ CORNERS),
        array=v,
        cmap=cmap.with_extremes(bad="lightgrey"),
        norm=norm,
        edgecolors="face",
        linewidths=0.2,
    )
    ax.add_collection(cells)
    cells.set_clip_path(outline)
    for (x, y), label, dy in zip(CORNERS, vertex_labels, (-0.04, -0.04, 0.04), strict=True):
        ax.text(x, y + dy, label, ha="center", va="top" if dy < 0 else "bottom")
    ax.set_xlim(-0.12, 1.12)
    ax.set_ylim(-0.1, 0.95)
    ax.set_aspect("equal")
    ax.set_axis_off()
    return cells


def plot_edge_tradeoffs(
    weights: ArrayLike,
    precision: ArrayLike,
    recall: ArrayLike,
    vertex_labels: Sequence[str] = LABELS,
    note: str = "",
) -> Figure:
    """Precision and recall (in %) along each edge of the triangle, one subplot per edge.

    An edge ``i → j`` holds the points whose third weight is 0; x is the weight of vertex j
    (0 at vertex i, 1 at vertex j). NaN values leave gaps in the lines.

    Args:
        weights: (K, 3) barycentric weights of the grid points.
        precision: (K,) fractions.
        recall: (K,) fractions.
        vertex_labels: names of the three vertices, in the weights' column order.
        note: small text line at the bottom; state the vertex scaling here.

    >>> w = np.array([[1, 0, 0], [0.5, 0.5, 0], [0, 1, 0], [0, 0, 1]])
    >>> fig = plot_edge_tradeoffs(w, [0.9, 0.6, 0.4, 0.8], [0.9, 0.95, 0.99, 0.7])
    >>> fig.axes[0].lines[0].get_xydata().tolist()  # precision from Robotistic to Altruistic
    [[0.0, 90.0], [0.5, 60.0], [1.0, 40.0]]
    """
    return next(edge_tradeoff_figures(weights, [("", precision, recall)], vertex_labels, note))[1]


def edge_tradeoff_figures(
    weights: ArrayLike,
    panels: Iterable[tuple],
    vertex_labels: Sequence[str] = LABELS,
    note: str = "",
) -> Iterator[tuple[str, Figure]]:
    """:func:`plot_edge_tradeoffs` of each ``(tag, precision, recall[, title])``, as
    ``(tag, figure)``; ``title`` (the class and RoI) above the three edges.

    All share one figure, redrawn for each: draw it before taking the next.

    >>> w = np.array([[1, 0, 0], [0, 1, 0], [0, 0, 1]])
    >>> panels = [(tag, [0.5, 0.5, 0.5], [p, p, p]) for tag, p in (("a", 0.2), ("b", 0.4))]
    >>> figures = edge_tradeoff_figures(w, panels)  # recall from Robotistic to Altruistic:
    >>> [(tag, fig.axes[0].lines[1].get_ydata().tolist()) for tag, fig in figures]
    [('a', [20.0, 20.0]), ('b', [40.0, 40.0])]
    """
    w = _weights(weights)
    edges = []  # (points on the edge in order of the weight of j, precision line, recall line)
    fig = None
    for tag, precision, recall, *title in panels:
        metrics = {
            "precision": _values(precision, len(w), "precision"),
            "recall": _values(recall, len(w), "recall"),
        }
        first = fig is None
        if first:
            fig = Figure(figsize=(12.0, 3.8), layout="constrained")
            axes = fig.subplots(1, 3, sharey=True)
            for ax, (i, j) in zip(axes, EDGES, strict=True):
                points = np.flatnonzero(np.abs(w[:, 3 - i - j]) < 1e-9)
                points = points[np.argsort(w[points, j], kind="stable")]
                lines = [
                    ax.plot(w[points, j], 100 * values[points], marker=marker, label=name)[0]
                    for (name, values), marker in zip(metrics.items(), "os", strict=True)
                ]
                edges.append((points, lines))
                _edge_axes(ax, i, j, vertex_labels, len(points) > 0)
            axes[0].set_ylabel("%")
            legend = axes[0].legend(loc="lower left")
            fig.supxlabel(note, fontsize="small", wrap=True)
            suptitle = fig.suptitle(title[0] if title else "")
            lines = [line for _, pair in edges for line in pair]
            redraw_only(freeze_layout(fig), [suptitle, *lines, legend])  # legend over lines
        suptitle.set_text(title[0] if title else "")
        for points, lines in edges:
            for line, values in zip(lines, metrics.values(), strict=True):
                line.set_ydata(100 * values[points])
        yield tag, fig


def _edge_axes(ax: Axes, i: int, j: int, vertex_labels: Sequence[str], has_points: bool) -> None:
    if not has_points:
        ax.text(0.5, 50, "no grid points on this edge", ha="center", va="center")
    ax.set_title(f"{vertex_labels[i]} → {vertex_labels[j]}")
    ax.set_xlabel(f"weight of {vertex_labels[j]}")
    ax.set_xlim(-0.03, 1.03)
    ax.set_ylim(0, 102)
    ax.grid(alpha=0.3)
