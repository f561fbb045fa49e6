"""Line plots: metrics against one parameter (the prior-adapted rule's α, the temperature),
reliability diagrams and risk–coverage curves; and the drawing jobs that make them
(:mod:`costseg.report.drawing`), which take plain values only."""

from __future__ import annotations

from collections.abc import Iterator, Mapping, Sequence

import numpy as np
from matplotlib.figure import Figure


def plot_curves(
    x: Sequence[float],
    series: Mapping[str, Sequence[float]],
    xlabel: str,
    title: str,
    subject: str = "",
) -> Figure:
    """One line per series over ``x``, values in [0, 1] (NaN points are left out by matplotlib);
    ``subject`` (the network and shift) under the title.

    >>> plot_curves([0, 1], {"recall": [0.5, 0.9]}, "α", "person").axes[0].get_xlabel()
    'α'
    """
    fig = Figure(figsize=(6, 4), dpi=100, layout="constrained")
    ax = fig.add_subplot()
    for label, values in series.items():
        ax.plot(x, values, marker="o", label=label)
    ax.set(xlabel=xlabel, ylabel="value", ylim=(0, 1.02))
    ax.set_title(f"{title}\n{subject}" if subject else title, wrap=True)
    ax.grid(alpha=0.3)
    ax.legend()
    return fig


Curves = tuple[str, Sequence[float], Mapping[str, Sequence[float]], str, str]
"""``(tag, x, series, xlabel, title)`` of one :func:`plot_curves` figure."""


def curve_figures(curves: Sequence[Curves], subject: str = "") -> Iterator[tuple[str, Figure]]:
    """``(tag, plot_curves(x, series, xlabel, title, subject))`` of each of ``curves`` (a
    drawing job).

    >>> [tag for tag, _ in curve_figures([("a", [0, 1], {"r": [0.5, 0.9]}, "α", "person")])]
    ['a']
    """
    for tag, x, series, xlabel, title in curves:
        yield tag, plot_curves(x, series, xlabel, title, subject)


def reliability_figures(ece: Mapping, subject: str = "") -> Iterator[tuple[str, Figure]]:
    """``reliability`` (where ``ece`` has bins; a job), titled with ``subject`` (the network
    and shift)."""
    if ece:
        yield "reliability", plot_reliability(ece, subject)


def plot_reliability(bins: Mapping[str, Mapping], subject: str = "") -> Figure:
    """Accuracy against confidence per bin, one line per set of probabilities (raw, scaled).

    >>> bins = {"confidence": np.array([0.5, 0.9]), "accuracy": np.array([0.4, 1.0]), "ece": 0.05}
    >>> plot_reliability({"raw": bins}).axes[0].get_xlabel()
    'confidence'
    """
    fig = Figure(figsize=(5, 5), layout="constrained")
    ax = fig.add_subplot()
    ax.plot([0, 1], [0, 1], color="grey", linestyle="--", label="perfect calibration")
    for name, b in bins.items():
        conf, acc = np.asarray(b["confidence"]), np.asarray(b["accuracy"])
        keep = np.isfinite(conf) & np.isfinite(acc)
        ax.plot(conf[keep], acc[keep], marker="o", label=f"{name} (ECE {float(b['ece']):.4f})")
    ax.set(xlabel="confidence", ylabel="accuracy", xlim=(0, 1), ylim=(0, 1))
    title = "reliability (top label, all pixels)"
    ax.set_title(f"{title}\n{subject}" if subject else title, wrap=True)
    ax.legend()
    return fig


Panel = tuple[str, str, list[tuple[str, tuple[list[float], list[float]]]]]
"""``(class name, axes title, [(rule label, (coverage, selective error))])`` of one axes of a
risk–coverage figure."""


def risk_coverage_figures(figures: Sequence[Sequence[Panel]], note: str) -> Iterator[tuple]:
    """``risk_coverage_<class>`` of each figure's panels, side by side, under ``note`` (the
    rules and defer costs, the network and shift) (a job).

    >>> panel = ("car", "car, RoI 0", [("ml", ([1.0, 0.5], [0.2, 0.1]))])
    >>> [tag for tag, _ in risk_coverage_figures([[panel]], "defer sweep")]
    ['risk_coverage_car']
    """
    for panels in figures:
        fig = Figure(figsize=(5 * len(panels), 4), dpi=100, layout="constrained")
        axes = fig.subplots(1, len(panels), squeeze=False)[0]
        for ax, (_, title, curves) in zip(axes, panels, strict=True):
            for label, (coverage, risk) in curves:
                ax.plot(coverage, risk, marker="o", markersize=3, label=label)
            ax.set(xlabel="coverage", ylabel="selective error", xlim=(0, 1.02))
            ax.set_title(title)
            ax.grid(alpha=0.3)
            ax.legend(fontsize=8)
        fig.suptitle(f"risk–coverage: {note}", fontsize=9, wrap=True)
        yield f"risk_coverage_{panels[0][0]}", fig
