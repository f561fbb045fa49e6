"""Figures of the paper: masks per decision rule, FP/FN heatmaps, RoIs, priors.

Each function returns a :class:`matplotlib.figure.Figure` built without pyplot, so nothing needs
a display or a global backend; save it with :func:`costseg.report.files.save_figure` or send it to
TensorBoard with :func:`costseg.report.tensorboard.log_figures`. The image is ``figsize * dpi``
pixels. Arrays may be numpy arrays or (CPU or GPU) tensors.

Figures of one kind and layout (the mask figures of several images, the FP and FN grids) come
from generators that build the figure once and redraw it with each one's data
(:func:`mask_figures`, :func:`heatmap_grid_figures`): building the axes and the layout, which
measures every text, cost more than drawing. Draw each figure before taking the next.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Iterator, Mapping, Sequence

import numpy as np
import torch
from matplotlib.colors import Normalize
from matplotlib.figure import Figure
from matplotlib.patches import Patch

from costseg.classes import CLASS_NAMES, DEFERRED_COLOUR, IGNORE_INDEX, PALETTE, colorize
from costseg.decision.label_maps import DEFERRED

ArrayLike = np.ndarray | torch.Tensor
PANEL = 3.0  # inches: width of one image panel


def freeze_layout(fig: Figure) -> Figure:
    """Run the figure's layout engine once and keep the positions it chose.

    A figure redrawn with new data of the same shape then skips the layout, which measures every
    text and takes about as long as drawing.

    >>> fig = Figure(layout="constrained")
    >>> ax = fig.subplots()
    >>> type(freeze_layout(fig).get_layout_engine()).__name__  # keeps positions, lays out nothing
    'PlaceHolderLayoutEngine'
    """
    engine = fig.get_layout_engine()
    if engine is not None:
        engine.execute(fig)
        fig.set_layout_engine("none")
    return fig


def as_numpy(x: ArrayLike) -> np.ndarray:
    """``x`` (a tensor on any device, or array-like) as a numpy array."""
    return x.detach().cpu().numpy() if isinstance(x, torch.Tensor) else np.asarray(x)


def _image(image: ArrayLike) -> np.ndarray:
    img = as_numpy(image)
    if img.ndim == 3 and img.shape[0] == 3 and img.shape[-1] != 3:
        img = img.transpose(1, 2, 0)  # datasets yield (3, H, W)
    if img.ndim != 3 or img.shape[-1] != 3 or img.dtype != np.uint8:
        raise ValueError(f"expected an (H, W, 3) uint8 image, got {img.shape} {img.dtype}")
    return img


def _masks(
    image: ArrayLike, target: ArrayLike, preds: Mapping[str, ArrayLike]
) -> tuple[np.ndarray, np.ndarray, dict[str, np.ndarray]]:
    img, gt = _image(image), as_numpy(target)
    masks = {name: as_numpy(p) for name, p in preds.items()}
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
        preds: rule name → (H, W) train ids, 255 = deferred (``DEFERRED_COLOUR``).

    Returns:
        (H, (2 + K) * W, 3) uint8 RGB.

    >>> image = np.zeros((2, 3, 3), np.uint8)
    >>> masks_side_by_side(image, np.zeros((2, 3)), {"ml": np.ones((2, 3))}).shape
    (2, 9, 3)
    """
    img, gt, masks = _masks(image, target, preds)
    decisions = (colorize(m, deferred=True) for m in masks.values())
    return np.concatenate([img, colorize(gt), *decisions], axis=1)


def _legend_handles(
    gt: np.ndarray, masks: Sequence[np.ndarray], class_names: Sequence[str]
) -> list[Patch]:
    """The classes present in the ground truth or a rule's mask; "ignore" for the ground
    truth's 255, "deferred" for a rule's."""
    present = np.unique(np.concatenate([m.ravel() for m in (gt, *masks)]).astype(np.int64))
    handles = [
        Patch(facecolor=PALETTE[i] / 255, edgecolor="grey", label=class_names[i])
        for i in present
        if i < len(class_names)
    ]
    if (gt == IGNORE_INDEX).any():
        handles.append(Patch(facecolor="black", label="ignore"))
    if any((m == DEFERRED).any() for m in masks):
        colour = np.array(DEFERRED_COLOUR) / 255
        handles.append(Patch(facecolor=colour, edgecolor="grey", label="deferred"))
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
        preds: rule name (panel title, e.g. "Altruistic") → (H, W) train ids, 255 = deferred
            (drawn in ``DEFERRED_COLOUR``, "deferred" in the legend).
        class_names: names of the train ids, for the legend of the classes present.

    >>> fig = plot_masks(np.zeros((4, 8, 3), np.uint8), np.zeros((4, 8)), {"ml": np.ones((4, 8))})
    >>> [ax.get_title() for ax in fig.axes], [t.get_text() for t in fig.legends[0].texts]
    (['image', 'ground truth', 'ml'], ['road', 'sidewalk'])
    >>> deferred = {"ml": np.full((4, 8), 255)}
    >>> fig = plot_masks(np.zeros((4, 8, 3), np.uint8), np.zeros((4, 8)), deferred)
    >>> [t.get_text() for t in fig.legends[0].texts]
    ['road', 'deferred']
    """
    return next(mask_figures([("", image, target, preds)], class_names))[1]


def mask_figures(
    examples: Iterable[tuple],
    class_names: Sequence[str] = CLASS_NAMES,
    subject: str = "",
) -> Iterator[tuple[str, Figure]]:
    """:func:`plot_masks` of each ``(tag, image, target, preds[, extra])``, as ``(tag, figure)``;
    ``extra``: title → (H, W, 3) uint8 panels drawn after the rules' (the uncertainty maps);
    ``subject`` (the network and shift) above the panels.

    Examples of one size, the same rules and a legend of as many rows share one figure, which
    is redrawn for each: draw it before taking the next.

    >>> examples = [(str(i), np.zeros((4, 8, 3), np.uint8), np.full((4, 8), i), {}) for i in (0, 1)]
    >>> [(tag, fig.legends[0].texts[0].get_text()) for tag, fig in mask_figures(examples)]
    [('0', 'road'), ('1', 'sidewalk')]
    """
    fig, layout, images = None, None, []
    for tag, image, target, preds, *extra in examples:
        img, gt, masks = _masks(image, target, preds)
        panels = {"image": img, "ground truth": colorize(gt)}
        panels |= {name: colorize(m, deferred=True) for name, m in masks.items()}
        panels |= extra[0] if extra else {}
        handles = _legend_handles(gt, list(masks.values()), class_names)
        ncols = max(1, min(len(handles), 10))
        if layout != (gt.shape, tuple(panels), -(-len(handles) // ncols)):
            layout = (gt.shape, tuple(panels), -(-len(handles) // ncols))
            height, width = gt.shape
            lines = max(title.count("\n") for title in panels)  # two-line titles: higher
            size = (PANEL * len(panels), PANEL * height / width + 0.8 + 0.2 * lines)
            fig = Figure(figsize=(size[0], size[1] + 0.3 * bool(subject)), layout="constrained")
            if subject:
                fig.suptitle(subject, fontsize="medium", wrap=True)
            images = []
            for ax, (title, rgb) in zip(fig.subplots(1, len(panels)), panels.items(), strict=True):
                images.append(ax.imshow(rgb, interpolation="nearest"))
                ax.set_title(title)
                ax.set_axis_off()
                ax.set_anchor("S" if lines else "C")  # the room above for the titles
            _mask_legend(fig, handles, ncols)
            freeze_layout(fig)
        else:
            for im, rgb in zip(images, panels.values(), strict=True):
                im.set_data(rgb)
            fig.legends[0].remove()
            _mask_legend(fig, handles, ncols)
        yield tag, fig


def example_mask_figures(
    names: Sequence[str], examples: Iterable[tuple], subject: str = ""
) -> Iterator[tuple[str, Figure]]:
    """``masks_<i>`` of each ``(image (H, W, 3), labels, preds (K, H, W), uncertainty maps)``:
    the image, the ground truth, the labels of each of the rules ``names`` and the uncertainty
    maps, each titled with its scale (docs/definitions.md §13), under ``subject``.

    >>> ex = (np.zeros((4, 8, 3), np.uint8), np.zeros((4, 8), np.uint8), np.zeros((1, 4, 8)), {})
    >>> [tag for tag, _ in example_mask_figures(["ml"], [ex])]
    ['masks_0']
    """
    from costseg.report.uncertainty import uncertainty_tiles

    tagged = (
        (
            f"masks_{i}",
            image,
            label,
            dict(zip(names, preds, strict=True)),
            {t.scale: t.rgb for t in uncertainty_tiles(maps, len(CLASS_NAMES))},
        )
        for i, (image, label, preds, maps) in enumerate(examples)
    )
    yield from mask_figures(tagged, subject=subject)


def _mask_legend(fig: Figure, handles: list[Patch], ncols: int) -> None:
    fig.legend(
        handles=handles, loc="outside lower center", ncols=ncols, fontsize="small", frameon=False
    )


def _heat(heat: ArrayLike) -> np.ndarray:
    arr = as_numpy(heat).astype(np.float64)
    if arr.ndim != 2:
        raise ValueError(f"expected an (h, w) heatmap, got shape {arr.shape}")
    return arr


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
    return next(heatmap_grid_figures([("", maps, kind)]))[1]


def heatmap_grid_figures(
    grids: Iterable[tuple[str, Mapping[tuple[str, str], ArrayLike], str]], subject: str = ""
) -> Iterator[tuple[str, Figure]]:
    """:func:`plot_heatmap_grid` of each ``(tag, maps, kind)``, as ``(tag, figure)``, titled
    with what they show and ``subject`` (the network and shift).

    Grids of the same (rule, class) panels and map size share one figure, redrawn for each:
    draw it before taking the next.

    >>> grids = [(kind, {("ml", "car"): np.eye(2)}, kind) for kind in ("FP", "FN")]
    >>> [fig.get_suptitle().splitlines() for _, fig in heatmap_grid_figures(grids, "net")][1]
    ['FN segments per class and rule, whole image', 'net']
    """
    layout = grid = None
    for tag, maps, kind in grids:
        if not maps:
            raise ValueError("expected at least one (rule, class) heatmap, got an empty mapping")
        arrays = {key: _heat(m) for key, m in maps.items()}
        # An all-zero set of maps still needs a non-empty colour range.
        vmax = max(float(np.nanmax(a, initial=0.0)) for a in arrays.values()) or 1.0
        shape = next(iter(arrays.values())).shape
        if layout != (tuple(arrays), shape):
            layout, grid = (tuple(arrays), shape), _HeatmapGrid(arrays, vmax, kind, subject)
            freeze_layout(grid.fig)
        else:
            grid.show(arrays, vmax, kind, subject)
        yield tag, grid.fig


def _what(kind: str, subject: str = "") -> str:
    """A heatmap grid's title: ``FP`` / ``FN`` segments, or a phrase such as "missed
    instances" as given, per class and rule; ``subject`` (network, shift) below it."""
    what = kind if " " in kind else f"{kind} segments"
    return f"{what} per class and rule, whole image" + (f"\n{subject}" if subject else "")


class _HeatmapGrid:
    """A grid of heatmap panels (rows: classes, columns: rules) with one shared colour bar."""

    def __init__(
        self, arrays: Mapping[tuple[str, str], np.ndarray], vmax: float, kind: str, subject: str
    ):
        rules = list(dict.fromkeys(rule for rule, _ in arrays))
        classes = list(dict.fromkeys(cls for _, cls in arrays))
        height, width = next(iter(arrays.values())).shape
        size = (PANEL * len(rules) + 1.0, 0.0)
        # the panels at least 1.5 inches high: the colour bar's label fits beside one row;
        # above them the title and the subject, wrapped at about 0.1 inches a character
        lines = 1 + math.ceil(0.1 * len(subject) / size[0])
        size = (size[0], max(1.5, PANEL * height / width * len(classes)) + 0.4 + 0.25 * lines)
        self.fig = Figure(figsize=size, layout="constrained")
        self.norm = Normalize(0, vmax)
        self.images = {}
        axes = self.fig.subplots(len(classes), len(rules), squeeze=False)
        for (i, cls), (j, rule) in ((c, r) for c in enumerate(classes) for r in enumerate(rules)):
            ax = axes[i, j]
            ax.set_xticks([])
            ax.set_yticks([])
            if (rule, cls) in arrays:
                image = ax.imshow(arrays[rule, cls], cmap="inferno", norm=self.norm)
                self.images[rule, cls] = image
            else:
                ax.text(0.5, 0.5, "not computed", ha="center", va="center", transform=ax.transAxes)
            if i == 0:
                ax.set_title(rule)
            if j == 0:
                ax.set_ylabel(cls)
        self.title = self.fig.suptitle(_what(kind, subject), wrap=True)
        self.bar = self.fig.colorbar(image, ax=axes, label="share of images", shrink=0.9)

    def show(
        self, arrays: Mapping[tuple[str, str], np.ndarray], vmax: float, kind: str, subject: str
    ) -> None:
        """The same panels with new maps, colour scale and title."""
        self.norm.vmax = vmax
        for key, image in self.images.items():
            image.set_data(arrays[key])
        self.title.set_text(_what(kind, subject))
        self.fig.set_layout_engine("constrained")  # the colour bar's new tick labels may be
        freeze_layout(self.fig)  # wider ("0.175" after "0.5"): place its label again
