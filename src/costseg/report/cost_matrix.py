"""Figures of cost matrices: log colour scale, rows = predicted class, columns = true class; a
defer row (docs/definitions.md §14) is the last row, labelled "defer".

The matrices of several rules share one figure (:func:`cost_matrix_figures`): its 19 × 2 class
ticks and the layout around them are built once per shape, and only the image, the colour scale,
the zeros and the title change.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator, Sequence

import numpy as np
from matplotlib import colormaps
from matplotlib.colors import LogNorm
from matplotlib.figure import Figure

from costseg.classes import CLASS_NAMES
from costseg.report.figures import ArrayLike, as_numpy, freeze_layout

TRUE_AXIS = "true class $k$ (column)"
PREDICTED_AXIS = r"predicted class $\hat{k}$ (row)"
"""The axes' labels: the indices of ``C[k̂, k]`` (docs/definitions.md §1), drawn distinct."""


def plot_cost_matrix(
    C: ArrayLike, class_names: Sequence[str] = CLASS_NAMES, title: str = ""
) -> Figure:
    """A cost matrix on a log colour scale; rows = predicted class, columns = true class.

    A zero (the diagonal, a defer cost of 0) has no logarithm: it is drawn white and marked "0".

    Args:
        C: (N, N) costs, or (N + 1, N) with a defer row.
        class_names: N names for the ticks.
        title: e.g. "egoistic".

    >>> print(plot_cost_matrix(np.ones((2, 2)) - np.eye(2), ["a", "b"]).axes[0].get_ylabel())
    predicted class $\\hat{k}$ (row)
    >>> fig = plot_cost_matrix(np.array([[0, 1], [1, 0], [0.5, 0.5]]), ["a", "b"])
    >>> [t.get_text() for t in fig.axes[0].get_yticklabels()]
    ['a', 'b', 'defer']
    """
    return next(cost_matrix_figures([("", C, title)], class_names))[1]


def cost_matrix_figures(
    matrices: Iterable[tuple[str, ArrayLike, str]], class_names: Sequence[str] = CLASS_NAMES
) -> Iterator[tuple[str, Figure]]:
    """:func:`plot_cost_matrix` of each ``(tag, C, title)``, as ``(tag, figure)``.

    All share one figure, redrawn for each: draw it before taking the next.

    >>> eye = np.eye(2)
    >>> figures = cost_matrix_figures([("a", 1 - eye, "a"), ("b", 2 - eye, "b")], ["x", "y"])
    >>> [(tag, fig.axes[0].images[0].norm.vmax) for tag, fig in figures]
    [('a', 10.0), ('b', 2.0)]
    """
    fig = image = None
    n = len(class_names)
    for tag, C, title in matrices:
        cost = as_numpy(C).astype(np.float64)
        if cost.shape not in ((n, n), (n + 1, n)):
            raise ValueError(
                f"expected a ({n}, {n}) cost matrix (or ({n + 1}, {n}) with a defer row) for "
                f"{n} class names, got {cost.shape}"
            )
        shown = np.ma.masked_where(~(np.isfinite(cost) & (cost > 0)), cost)
        lo, hi = float(shown.min()), float(shown.max())
        if lo == hi:  # e.g. the robotistic matrix: a log colour bar needs a non-empty range
            lo, hi = lo / 10, hi * 10
        first = image is None or image.get_array().shape != cost.shape
        if first:
            fig, image = _figure(shown, LogNorm(lo, hi), class_names)
        else:
            image.set_data(shown)
            image.set_norm(LogNorm(lo, hi))
        ax = image.axes
        for text in list(ax.texts):
            text.remove()
        for i, j in zip(*np.nonzero(cost == 0), strict=True):
            ax.text(j, i, "0", ha="center", va="center", fontsize="x-small")
        ax.set_title(title)
        if first:
            freeze_layout(fig)
        yield tag, fig


def _figure(shown: np.ma.MaskedArray, norm: LogNorm, class_names: Sequence[str]):
    """The figure, axes, ticks and colour bar of an N × N (or (N + 1) × N) cost matrix; returns
    (figure, image)."""
    n = len(class_names)
    rows = [*class_names, "defer"][: shown.shape[0]]
    side = max(4.0, 0.3 * n + 2.5)
    fig = Figure(figsize=(side + 1.0, side + 0.3 * (len(rows) - n)), layout="constrained")
    ax = fig.subplots()
    cmap = colormaps["viridis"].with_extremes(bad="white")
    image = ax.imshow(shown, cmap=cmap, norm=norm, interpolation="nearest")
    ax.set_xticks(range(n), class_names, rotation=90)
    ax.set_yticks(range(len(rows)), rows)
    # mathtext: a combining hat (k̂) is lost in the default font and both axes would read "k"
    ax.set_xlabel(TRUE_AXIS)
    ax.set_ylabel(PREDICTED_AXIS)
    fig.colorbar(image, ax=ax, label="cost (log scale)", shrink=0.8)
    return fig, image
