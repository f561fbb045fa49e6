"""The figures of segment meta classification and fusion (docs/definitions.md §15), drawn by
figure workers from NumPy arrays: per example image the segments coloured by their true and
predicted IoU (MetaSeg's figure), the scatter of predicted against true IoU per rule, the
feature importances, and the fused rules' trade-off along τ.
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping, Sequence

import numpy as np
from matplotlib.figure import Figure

from costseg.meta.features import painted

IOU_COLOURS = "RdYlGn"  # red: IoU 0 (a false segment), green: 1
TOP_FEATURES = 15


def segment_iou_figures(
    examples: Sequence[tuple[str, str, np.ndarray, np.ndarray, np.ndarray, np.ndarray]],
) -> Iterator[tuple[str, Figure]]:
    """Per ``(tag, title, image (H, W, 3) uint8, ids (H, W), true IoU (n,), predicted IoU
    (n,))``: the image, the segments by true IoU and by predicted IoU, under ``title`` (the
    rule, the meta model, the network and shift)."""
    for tag, title, image, ids, true, predicted in examples:
        h, w = ids.shape
        fig = Figure(figsize=(12, 12 * h / w / 3 + 1.2), layout="constrained")
        fig.suptitle(title, wrap=True)
        axes = fig.subplots(1, 3)
        axes[0].imshow(image)
        axes[0].set_title("image")
        for ax, values, name in (
            (axes[1], true, "true IoU"),
            (axes[2], predicted, "predicted IoU"),
        ):
            shown = ax.imshow(painted(ids, values), cmap=IOU_COLOURS, vmin=0, vmax=1)
            ax.set_facecolor("0.5")  # no segment (ignored or deferred pixels): grey
            ax.set_title(f"segments: {name}")
        for ax in axes:
            ax.set_xticks([]), ax.set_yticks([])
        fig.colorbar(shown, ax=axes, shrink=0.8, label="IoU")
        yield tag, fig


def iou_scatter_figures(
    rules: Sequence[str],
    true: Sequence[np.ndarray],
    predicted: Mapping[str, Sequence[np.ndarray]],
    subject: str = "",
) -> Iterator[tuple[str, Figure]]:
    """One panel per rule: each segment's predicted IoU (one colour per model) against its true
    (adjusted) IoU, with the diagonal; ``subject`` (the network and shift) in the title."""
    fig = Figure(figsize=(4 * len(rules), 4.4), layout="constrained")
    title = "meta regression: each segment's predicted against its true IoU, per rule"
    fig.suptitle(f"{title}\n{subject}" if subject else title, wrap=True)
    axes = np.atleast_1d(fig.subplots(1, len(rules), squeeze=False)[0])
    for k, (ax, rule) in enumerate(zip(axes, rules, strict=True)):
        for model, values in predicted.items():
            ax.scatter(true[k], values[k], s=4, alpha=0.35, label=model)
        ax.plot([0, 1], [0, 1], color="k", lw=1, ls="--")
        ax.set(xlim=(0, 1), ylim=(0, 1), xlabel="true IoU", ylabel="predicted IoU", title=rule)
        ax.legend(fontsize=7, markerscale=3)
    yield "meta/iou_scatter", fig


def importance_figures(
    rules: Sequence[str],
    importances: Sequence[Mapping[str, float]],
    model: str,
    subject: str = "",
) -> Iterator[tuple[str, Figure]]:
    """One panel per rule: the classifier's largest feature importances; ``subject`` (the
    network and shift) in the title."""
    fig = Figure(figsize=(4 * len(rules), 4.9), layout="constrained")
    title = f"meta classification ({model}): the largest feature importances, per rule"
    fig.suptitle(f"{title}\n{subject}" if subject else title, wrap=True)
    axes = np.atleast_1d(fig.subplots(1, len(rules), squeeze=False)[0])
    for ax, rule, values in zip(axes, rules, importances, strict=True):
        top = sorted(values.items(), key=lambda kv: kv[1], reverse=True)[:TOP_FEATURES][::-1]
        ax.barh([k for k, _ in top], [v for _, v in top], color="tab:blue")
        ax.set(title=f"{rule} ({model})", xlabel="importance")
        ax.tick_params(axis="y", labelsize=7)
    yield "meta/feature_importance", fig


def tradeoff_figures(
    panels: Sequence[tuple[str, np.ndarray, np.ndarray, Mapping[str, tuple[float, float]]]],
    taus: Sequence[float],
    y_label: str,
    subject: str = "",
) -> Iterator[tuple[str, Figure]]:
    """Per ``(title, FP segments along τ, y along τ, marks {rule: (fp, y)})`` one panel: the
    fused rule's curve over τ, the base and the unfused rule marked; ``subject`` (the network
    and shift) in the title."""
    fig = Figure(figsize=(4.5 * len(panels), 4.4), layout="constrained")
    title = f"fusion along τ: false-positive segments against {y_label}"
    fig.suptitle(f"{title}\n{subject}" if subject else title, wrap=True)
    axes = np.atleast_1d(fig.subplots(1, len(panels), squeeze=False)[0])
    for ax, (title, fp, y, marks) in zip(axes, panels, strict=True):
        ax.plot(fp, y, marker="o", color="tab:blue", label="fused, along τ")
        for t, x, v in zip(taus, fp, y, strict=True):
            ax.annotate(f"{t:g}", (x, v), fontsize=7, xytext=(3, 3), textcoords="offset points")
        for (rule, (x, v)), marker in zip(marks.items(), ("s", "^", "D", "v"), strict=False):
            ax.scatter([x], [v], marker=marker, s=60, zorder=3, label=rule)
        ax.set(title=title, xlabel="false-positive segments", ylabel=y_label)
        ax.legend(fontsize=7)
    yield f"fusion/{y_label.replace(' ', '_')}", fig
