"""Line plots of metrics against one parameter (e.g. the prior-adapted rule's α)."""

from __future__ import annotations

from collections.abc import Mapping, Sequence

from matplotlib.figure import Figure


def plot_curves(
    x: Sequence[float], series: Mapping[str, Sequence[float]], xlabel: str, title: str
) -> Figure:
    """One line per series over ``x``, values in [0, 1] (NaN points are left out by matplotlib).

    >>> plot_curves([0, 1], {"recall": [0.5, 0.9]}, "α", "person").axes[0].get_xlabel()
    'α'
    """
    fig = Figure(figsize=(6, 4), dpi=100, layout="constrained")
    ax = fig.add_subplot()
    for label, values in series.items():
        ax.plot(x, values, marker="o", label=label)
    ax.set(xlabel=xlabel, ylabel="value", title=title, ylim=(0, 1.02))
    ax.grid(alpha=0.3)
    ax.legend()
    return fig
