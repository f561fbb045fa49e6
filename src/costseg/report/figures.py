"""Figures of the paper: masks per decision rule, FP/FN heatmaps, cost matrices, RoIs, priors.

Each function returns a :class:`matplotlib.figure.Figure` built without pyplot, so nothing needs
a display or a global backend; save it with :func:`costseg.report.files.save_figure` or send it to
TensorBoard with :func:`costseg.report.tensorboard.log_figures`. The image is ``figsize * dpi``
pixels. Arrays may be numpy arrays or (CPU or GPU) tensors.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np
import torch
from matplotlib import colormaps
from matplotlib.colors import LogNorm
from matplotlib.figure import Figure
from matplotlib.patches import Patch

from costseg.classes import CLASS_NAMES, IGNORE_INDEX, PALETTE, colorize

ArrayLike = np.ndarray | torch.Tensor
PANEL = 3.0  # inches: width of one image panel


def _numpy(x: ArrayLike) -> np.ndarray:
    return x.detach().cpu().numpy() if isinstance(x, torch.Tensor) else np.asarray(x)


def _image(image: ArrayLike) -> np.ndarray:
    img = _numpy(image)
    if img.ndim == 3 and img.shape[0] == 3 and img.shape[-1] != 3:
        img = img.transpose(1, 2, 0)  # datasets yield (3, H, W)
    if img.ndim != 3 or img.shape[-1] != 3 or img.dtype != np.uint8:
        raise ValueError(f"expected an (H, W, 3) uint8 image, got {img.shape} {img.dtype}")
    return img


def _masks(
    image: ArrayLike, target: ArrayLike, preds: Mapping[str, ArrayLike]
) -> tuple[np.ndarray, np.ndarray, dict[str, np.ndarray]]:
    img, gt = _image(image), _numpy(target)
    masks = {name: _numpy(p) for name, p in preds.items()}
    for name, m in {"target": gt, **masks}.items():
        if m.shape != img.shape[:2]:
            raise ValueError(
                f"expected {name} of shape {img.shape[:2]} like the image, got {m.shape}"
            )
    return img, gt, masks


def masks_side_by_side(
    image: ArrayLike, target: ArrayLike, preds: Mapping[str, ArrayLike]
) -> np.ndarray:
    """The image, the colourised ground truth and each rule's mask, left to right.

    Args:
        image: (H, W, 3) or (3, H, W) uint8.
        target: (H, W) train ids, 255 = ignore (black).
        preds: rule name → (H, W) train ids.

    Returns:
        (H, (2 + K) * W, 3) uint8 RGB.

    >>> image = np.zeros((2, 3, 3), np.uint8)
    >>> masks_side_by_side(image, np.zeros((2, 3)), {"ml": np.ones((2, 3))}).shape
    (2, 9, 3)
    """
    img, gt, masks = _masks(image, target, preds)
    return np.concatenate([img, colorize(gt), *(colorize(m) for m in masks.values())], axis=1)


def _legend_handles(masks: Sequence[np.ndarray], class_names: Sequence[str]) -> list[Patch]:
    present = np.unique(np.concatenate([m.ravel() for m in masks]).astype(np.int64))
    handles = [
        Patch(facecolor=PALETTE[i] / 255, edgecolor="grey", label=class_names[i])
        for i in present
        if i < len(class_names)
    ]
    if IGNORE_INDEX in present:
        handles.append(Patch(facecolor="black", label="ignore"))
    return handles


def plot_masks(
    image: ArrayLike,
    target: ArrayLike,
    preds: Mapping[str, ArrayLike],
    class_names: Sequence[str] = CLASS_NAMES,
) -> Figure:
    """Image, ground truth and one mask per decision rule side by side (the paper's mask figure).

    Args:
        image: (H, W, 3) or (3, H, W) uint8.
        target: (H, W) train ids, 255 = ignore.
        preds: rule name (panel title, e.g. "Altruistic") → (H, W) train ids.
        class_names: names of the train ids, for the legend of the classes present.

    >>> fig = plot_masks(np.zeros((4, 8, 3), np.uint8), np.zeros((4, 8)), {"ml": np.ones((4, 8))})
    >>> [ax.get_title() for ax in fig.axes], [t.get_text() for t in fig.legends[0].texts]
    (['image', 'ground truth', 'ml'], ['road', 'sidewalk'])
    """
    img, gt, masks = _masks(image, target, preds)
    panels = {"image": img, "ground truth": colorize(gt)}
    panels |= {name: colorize(m) for name, m in masks.items()}
    height, width = gt.shape
    fig = Figure(figsize=(PANEL * len(panels), PANEL * height / width + 0.8), layout="constrained")
    for ax, (title, rgb) in zip(fig.subplots(1, len(panels)), panels.items(), strict=True):
        ax.imshow(rgb, interpolation="nearest")
        ax.set_title(title)
        ax.set_axis_off()
    handles = _legend_handles([gt, *masks.values()], class_names)
    fig.legend(
        handles=handles,
        loc="outside lower center",
        ncols=min(len(handles), 10),
        fontsize="small",
        frameon=False,
    )
    return fig


def _heat(heat: ArrayLike) -> np.ndarray:
    arr = _numpy(heat).astype(np.float64)
    if arr.ndim != 2:
        raise ValueError(f"expected an (h, w) heatmap, got shape {arr.shape}")
    return arr


def plot_heatmap(heat: ArrayLike, title: str, vmax: float | None = None) -> Figure:
    """How often each location lies in a false positive / negative segment, with a colour bar.

    Args:
        heat: (h, w) counts or frequencies.
        title: e.g. "FP person, egoistic".
        vmax: top of the colour scale (default: the map's maximum); the bottom is 0.

    >>> plot_heatmap(np.eye(4), "FP person").axes[0].get_title()
    'FP person'
    """
    arr = _heat(heat)
    height, width = arr.shape
    fig = Figure(figsize=(6.0, 6.0 * height / width + 0.6), layout="constrained")
    ax = fig.subplots()
    im = ax.imshow(arr, cmap="inferno", vmin=0, vmax=vmax, interpolation="nearest")
    ax.set_title(title)
    ax.set_axis_off()
    fig.colorbar(im, ax=ax, label="frequency", shrink=0.9)
    return fig


def plot_heatmap_grid(maps: Mapping[tuple[str, str], ArrayLike], kind: str = "FP") -> Figure:
    """Heatmaps of ``kind`` segments as in the paper: one row per class, one column per rule.

    All panels share one colour scale (0 to the largest value of any map) and one colour bar.

    Args:
        maps: (rule, class name) → (h, w) map; rows and columns follow first appearance.
        kind: "FP" or "FN", used in the titles.

    >>> fig = plot_heatmap_grid({("egoistic", "person"): np.eye(3), ("ml", "car"): np.eye(3)})
    >>> len(fig.axes)  # 2 x 2 panels and the colour bar
    5
    """
    if not maps:
        raise ValueError("expected at least one (rule, class) heatmap, got an empty mapping")
    arrays = {key: _heat(m) for key, m in maps.items()}
    rules = list(dict.fromkeys(rule for rule, _ in arrays))
    classes = list(dict.fromkeys(cls for _, cls in arrays))
    # An all-zero set of maps still needs a non-empty colour range.
    vmax = max(float(np.nanmax(a, initial=0.0)) for a in arrays.values()) or 1.0
    height, width = next(iter(arrays.values())).shape
    size = (PANEL * len(rules) + 1.0, PANEL * height / width * len(classes) + 0.6)
    fig = Figure(figsize=size, layout="constrained")
    axes = fig.subplots(len(classes), len(rules), squeeze=False)
    for (i, cls), (j, rule) in ((c, r) for c in enumerate(classes) for r in enumerate(rules)):
        ax = axes[i, j]
        ax.set_xticks([])
        ax.set_yticks([])
        if (rule, cls) in arrays:
            im = ax.imshow(arrays[rule, cls], cmap="inferno", vmin=0, vmax=vmax)
        else:
            ax.text(0.5, 0.5, "not computed", ha="center", va="center", transform=ax.transAxes)
        if i == 0:
            ax.set_title(rule)
        if j == 0:
            ax.set_ylabel(cls)
    fig.suptitle(f"{kind} segments")
    fig.colorbar(im, ax=axes, label=f"{kind} segment frequency", shrink=0.9)
    return fig


def plot_cost_matrix(
    C: ArrayLike, class_names: Sequence[str] = CLASS_NAMES, title: str = ""
) -> Figure:
    """A cost matrix on a log colour scale; rows = predicted class, columns = true class.

    The zero diagonal has no logarithm: it is drawn white and marked "0".

    Args:
        C: (N, N) costs.
        class_names: N names for the ticks.
        title: e.g. "egoistic".

    >>> plot_cost_matrix(np.ones((2, 2)) - np.eye(2), ["a", "b"]).axes[0].get_ylabel()
    'predicted class k̂'
    """
    cost = _numpy(C).astype(np.float64)
    n = len(class_names)
    if cost.shape != (n, n):
        raise ValueError(f"expected a ({n}, {n}) cost matrix for {n} class names, got {cost.shape}")
    shown = np.ma.masked_where(~(np.isfinite(cost) & (cost > 0)), cost)
    lo, hi = float(shown.min()), float(shown.max())
    if lo == hi:  # e.g. the robotistic matrix: a log colour bar needs a non-empty range
        lo, hi = lo / 10, hi * 10
    side = max(4.0, 0.3 * n + 2.5)
    fig = Figure(figsize=(side + 1.0, side), layout="constrained")
    ax = fig.subplots()
    cmap = colormaps["viridis"].with_extremes(bad="white")
    im = ax.imshow(shown, cmap=cmap, norm=LogNorm(lo, hi), interpolation="nearest")
    for i in np.flatnonzero(np.diag(cost) == 0):
        ax.text(i, i, "0", ha="center", va="center", fontsize="x-small")
    ax.set_xticks(range(n), class_names, rotation=90)
    ax.set_yticks(range(n), class_names)
    ax.set_xlabel("true class k")
    ax.set_ylabel("predicted class k̂")
    ax.set_title(title)
    fig.colorbar(im, ax=ax, label="cost (log scale)", shrink=0.8)
    return fig
