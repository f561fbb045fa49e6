"""Figures of a designed value system (docs/definitions.md §20): the designed matrix beside the
robotistic one, and the Pareto front of the search (each constraint's risk on the search images
against the objective, certified candidates marked, the levels α drawn). Plain NumPy in, so a
figure worker draws them without torch."""

from __future__ import annotations

from collections.abc import Iterator, Sequence

import numpy as np
from matplotlib.colors import LogNorm
from matplotlib.figure import Figure

from costseg.report.cost_matrix import PREDICTED_AXIS, TRUE_AXIS


def matrices_figure(
    matrices: Sequence[tuple[str, np.ndarray]], class_names: Sequence[str], title: str
) -> Figure:
    """The matrices side by side on one log colour scale (rows predicted, columns true; a defer
    row last); a zero is white.

    >>> fig = matrices_figure([("a", 1 - np.eye(2)), ("b", 3 - 2 * np.eye(2))], ["x", "y"], "t")
    >>> [ax.get_title() for ax in fig.axes[:2]]
    ['a', 'b']
    """
    shown = [np.ma.masked_where(~(c > 0), c.astype(np.float64)) for _, c in matrices]
    lo = min(float(s.min()) for s in shown)
    hi = max(float(s.max()) for s in shown)
    norm = LogNorm(lo, hi if hi > lo else lo * 10)
    n = len(class_names)
    fig = Figure(figsize=(6.5 * len(matrices), 6.5), layout="constrained")
    axes = fig.subplots(1, len(matrices), squeeze=False)[0]
    for ax, (name, _), values in zip(axes, matrices, shown, strict=True):
        image = ax.imshow(values, norm=norm, cmap="viridis")
        rows = [*class_names, "defer"][: values.shape[0]]
        ax.set_xticks(range(n), class_names, rotation=90, fontsize=7)
        ax.set_yticks(range(len(rows)), rows, fontsize=7)
        ax.set_xlabel(TRUE_AXIS)
        ax.set_ylabel(PREDICTED_AXIS)
        ax.set_title(name)
    fig.colorbar(image, ax=list(axes), shrink=0.8, label="cost (log scale)")
    fig.suptitle(title)
    return fig


def front_figure(
    risks: np.ndarray,
    objective: np.ndarray,
    front: np.ndarray,
    certified: np.ndarray,
    chosen: int | None,
    constraints: Sequence[str],
    alphas: Sequence[float],
    objective_name: str,
    title: str,
    risks_d2: np.ndarray | None = None,
    order: np.ndarray | None = None,
) -> Figure:
    """Per constraint, every candidate's risk on the search images against its objective: the
    Pareto front (those the fixed-sequence test reached, and those after the candidate at which
    it stopped, never tested), the certified candidates and the chosen one marked, each tested
    candidate's certification risk beside its search risk, α as a line; one legend for all.

    >>> fig = front_figure(np.array([[0.1], [0.3]]), np.array([0.9, 0.95]), np.array([0, 1]),
    ...                    np.array([0]), 0, ["person:roi1:recall>=0.8"], [0.2], "agreement", "t",
    ...                    np.array([[0.12], [0.5]]), np.array([0, 1]))
    >>> len(fig.axes), len(fig.legends[0].get_texts())
    (1, 7)
    """
    k = len(constraints)
    order = front if order is None else order
    reached = order[: len(certified) + 1]  # the certified ones and the first that failed
    untested = np.setdiff1d(front, reached)
    fig = Figure(figsize=(4.5 * k, 4.8), layout="constrained")
    axes = fig.subplots(1, k, squeeze=False)[0]
    for i, ax in enumerate(axes):
        ax.scatter(risks[:, i], objective, s=6, c="0.75", label="candidates")
        ax.scatter(risks[reached, i], objective[reached], s=14, c="tab:blue",
                   label="Pareto front, tested")  # fmt: skip
        ax.scatter(risks[untested, i], objective[untested], s=14, facecolors="none",
                   edgecolors="tab:blue", label="Pareto front, untested (the test stopped "
                   "before it)")  # fmt: skip
        if len(certified):
            ax.scatter(risks[certified, i], objective[certified], s=22, c="tab:green",
                       label="certified")  # fmt: skip
        if risks_d2 is not None and len(reached):
            ax.scatter(risks_d2[reached, i], objective[reached], s=18, marker="x", c="k",
                       linewidths=0.8, label="tested: certification risk")  # fmt: skip
        if chosen is not None:
            ax.scatter(risks[chosen, i], objective[chosen], s=140, marker="*", c="tab:red",
                       label="chosen")  # fmt: skip
        ax.axvline(alphas[i], color="tab:red", linestyle="--", linewidth=1, label="α")
        ax.set_xlabel(f"risk of {constraints[i]}")
        ax.set_ylabel(f"{objective_name} (search images)")
    handles, labels = axes[0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="outside lower center", ncols=min(4, len(labels)),
               fontsize=7)  # fmt: skip
    fig.suptitle(f"{title}\nrisks on the search images (certification risks: x)")
    return fig


def design_figures(
    matrices: Sequence[tuple[str, np.ndarray]],
    class_names: Sequence[str],
    fronts: Sequence[tuple[str, tuple]],
    title: str,
) -> Iterator[tuple[str, Figure]]:
    """The figures of a design: ``design_matrices`` (when a matrix was designed) and one
    ``design_front_<space>`` per searched space (``fronts``: (space, :func:`front_figure`'s
    arguments before the title, those after it))."""
    if matrices:
        yield "design_matrices", matrices_figure(matrices, class_names, title)
    for space, arguments, tested in fronts:
        yield f"design_front_{space}", front_figure(*arguments, f"{title}: {space} space", *tested)
