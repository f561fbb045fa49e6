"""The value-space triangle (SPEC §2): heatmaps over barycentric weights and trade-offs per edge.

A grid point ``(α, β, γ)`` (``α + β + γ = 1``) stands for the mixture ``α C_0 + β C_1 + γ C_2`` of
three vertex matrices, by default ``C_R, C_A, C_E``. Mixing is not scale invariant, so every
figure carries a ``note`` line that should say how the vertices were scaled.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch
from matplotlib import colormaps
from matplotlib.collections import PolyCollection
from matplotlib.colors import Normalize
from matplotlib.figure import Figure
from matplotlib.patches import Polygon
from scipy.spatial import cKDTree

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


def barycentric_to_cartesian(weights: ArrayLike) -> np.ndarray:
    """Project barycentric weights onto the equilateral triangle of side 1 with :data:`CORNERS`.

    Args:
        weights: (K, 3) rows (α, β, γ), non-negative, summing to 1.

    Returns:
        (K, 2) cartesian points ``weights @ CORNERS``.

    >>> barycentric_to_cartesian([[1, 0, 0], [1 / 3, 1 / 3, 1 / 3]]).round(4).tolist()
    [[0.0, 0.0], [0.5, 0.2887]]
    """
    return _weights(weights) @ CORNERS


def _cells(xy: np.ndarray) -> np.ndarray:
    # Each point gets the hexagon of the triangular lattice around it (its Voronoi cell);
    # the spacing is the nearest-neighbour distance, i.e. the grid step h on the unit triangle.
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
    w = _weights(weights)
    v = _values(values, len(w), "values")
    fig = Figure(figsize=(5.5, 4.5), layout="constrained")
    ax = fig.subplots()
    outline = Polygon(CORNERS, closed=True, fill=False, edgecolor="black", linewidth=1.0)
    ax.add_patch(outline)
    cells = PolyCollection(
        _cells(w @ CORNERS),
        array=np.ma.masked_invalid(v),
        cmap=colormaps[cmap].with_extremes(bad="lightgrey"),
        norm=Normalize(vmin, vmax),
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
    ax.set_title(title)
    fig.colorbar(cells, ax=ax, label=cbar_label, shrink=0.8)
    fig.supxlabel(note, fontsize="small")
    return fig


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
    w = _weights(weights)
    metrics = {
        "precision": _values(precision, len(w), "precision"),
        "recall": _values(recall, len(w), "recall"),
    }
    fig = Figure(figsize=(12.0, 3.8), layout="constrained")
    axes = fig.subplots(1, 3, sharey=True)
    for ax, (i, j) in zip(axes, EDGES, strict=True):
        on_edge = np.abs(w[:, 3 - i - j]) < 1e-9
        order = np.argsort(w[on_edge, j], kind="stable")
        x = w[on_edge, j][order]
        for (name, values), marker in zip(metrics.items(), "os", strict=True):
            ax.plot(x, 100 * values[on_edge][order], marker=marker, label=name)
        if not on_edge.any():
            ax.text(0.5, 50, "no grid points on this edge", ha="center", va="center")
        ax.set_title(f"{vertex_labels[i]} → {vertex_labels[j]}")
        ax.set_xlabel(f"weight of {vertex_labels[j]}")
        ax.set_xlim(-0.03, 1.03)
        ax.set_ylim(0, 102)
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("%")
    axes[0].legend(loc="lower left")
    fig.supxlabel(note, fontsize="small")
    return fig
