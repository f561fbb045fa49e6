"""Figures of a monitored stream (docs/definitions.md §22): each requirement's running risk of the
monitored and the fixed matrix against α and the long-run bound, the shift's onset marked; θ
frame by frame. Plain NumPy in, so a figure worker draws them without torch."""

from __future__ import annotations

from collections.abc import Iterator, Sequence

import numpy as np
from matplotlib.figure import Figure


def monitor_figures(
    running: np.ndarray,
    fixed_running: np.ndarray,
    bounds: np.ndarray,
    theta: np.ndarray,
    texts: Sequence[str],
    alphas: Sequence[float],
    onset: int | None,
    scale: str,
    title: str,
) -> Iterator[tuple[str, Figure]]:
    """``monitor_risk`` and ``monitor_theta``.

    Args:
        running, fixed_running, bounds: (T, K) running risks of the monitored and the fixed
            matrix, and the bound after each frame.
        theta: (T, K) θ_t each frame was decided with.
        texts, alphas: the K requirements and their levels.
        onset: the position of the first shifted frame, or None.
        scale: the scale of θ (``log`` or ``mu``), for the axis.
        title: the figures' subject.
    """
    frames = np.arange(1, len(running) + 1)
    k = len(texts)
    fig = Figure(figsize=(6.4, 0.6 + 2.4 * k), dpi=100, layout="constrained")
    axes = fig.subplots(k, 1, squeeze=False)[:, 0]
    for i, ax in enumerate(axes):
        ax.plot(frames, fixed_running[:, i], color="tab:gray", label="fixed matrix")
        ax.plot(frames, running[:, i], color="tab:blue", label="monitored")
        ax.plot(frames, bounds[:, i], color="tab:blue", ls=":", lw=1, label="long-run bound")
        ax.axhline(alphas[i], color="tab:red", ls="--", lw=1, label=f"α = {alphas[i]:.3g}")
        _onset(ax, onset)
        ax.set_ylim(-0.02, 1.02)
        ax.set_ylabel("running risk")
        ax.set_title(texts[i], fontsize=9)
    axes[-1].set_xlabel("frame")
    axes[0].legend(fontsize=7, loc="upper right")
    fig.suptitle(f"running risk (fixed matrix and monitored)\n{title}", fontsize=8)
    yield "monitor_risk", fig

    fig = Figure(figsize=(6.4, 3.2), dpi=100, layout="constrained")
    ax = fig.add_subplot()
    for i, text in enumerate(texts):
        ax.step(frames, theta[:, i], where="post", label=text)
    _onset(ax, onset)
    ax.set_xlabel("frame")
    ax.set_ylabel("θ = log(1 + μ)" if scale == "log" else "θ = μ")
    ax.legend(fontsize=7)
    fig.suptitle(f"multipliers θ per requirement\n{title}", fontsize=8)
    yield "monitor_theta", fig


def _onset(ax, onset: int | None) -> None:
    if onset is not None:
        ax.axvline(onset + 0.5, color="black", lw=1, ls="-.", label="shift onset")
