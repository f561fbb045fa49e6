"""One picture per image: the image, each rule's overlay with a class-colour legend, where each
rule differs from argmax, and the uncertainty maps (docs/definitions.md §13); a rule that may
defer (docs/definitions.md §14) draws its deferred pixels in ``DEFERRED_COLOUR`` and states its
defer cost and deferred share. Drawn with numpy and PIL (fast enough for every video frame)."""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np
from PIL import Image, ImageDraw, ImageFont

from costseg.classes import CLASS_NAMES, DEFERRED_COLOUR, colorize
from costseg.decision.label_maps import DEFERRED
from costseg.report.uncertainty import Tile, draw_title, iou_tile, uncertainty_tiles

MAX_TILE_WIDTH = 512
MIN_TILE_WIDTH = 192  # room for the titles
TITLE = 16  # pixels above each tile; two lines (a rule that defers) take 2 * TITLE - 4
SWATCH = 14
ALPHA = 0.55  # weight of the class colour in an overlay


def overlay(image: np.ndarray, labels: np.ndarray) -> np.ndarray:
    """(H, W, 3) uint8: the image blended with the label map's class colours (deferred pixels:
    ``DEFERRED_COLOUR``)."""
    colours = colorize(labels, deferred=True).astype(np.float32)
    mixed = (1 - ALPHA) * image.astype(np.float32) + ALPHA * colours
    return mixed.round().astype(np.uint8)


def differences(image: np.ndarray, labels: np.ndarray, argmax: np.ndarray) -> np.ndarray:
    """(H, W, 3) uint8: the image greyed and darkened; where ``labels`` differ from ``argmax``,
    the rule's class colour (a deferred pixel: ``DEFERRED_COLOUR``)."""
    grey = image.astype(np.float32) @ np.float32([0.299, 0.587, 0.114])
    out = np.repeat((0.35 * grey).round().astype(np.uint8)[..., None], 3, axis=2)
    differ = labels != argmax
    out[differ] = colorize(labels[differ], deferred=True)
    return out


def _resized_values(values: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """(H, W) float values at ``size`` by nearest neighbour (segment values stay exact)."""
    rows = np.arange(size[0]) * values.shape[0] // size[0]
    cols = np.arange(size[1]) * values.shape[1] // size[1]
    return values[rows[:, None], cols]


def _tile_size(height: int, width: int) -> tuple[int, int]:
    scale = min(MAX_TILE_WIDTH / width, max(1.0, MIN_TILE_WIDTH / width))
    return max(1, round(height * scale)), max(1, round(width * scale))


def _resized(array: np.ndarray, size: tuple[int, int], nearest: bool) -> np.ndarray:
    if array.shape[:2] == size:
        return array
    method = Image.Resampling.NEAREST if nearest else Image.Resampling.BILINEAR
    return np.asarray(Image.fromarray(array).resize((size[1], size[0]), method))


def panel(
    image: np.ndarray,
    rule_names: Sequence[str],
    maps: np.ndarray,
    argmax: np.ndarray,
    defer_costs: Sequence[str | None] | None = None,
    uncertainty: Mapping[str, np.ndarray] | None = None,
    segment_iou: Sequence[np.ndarray] | None = None,
) -> np.ndarray:
    """The panel of one image.

    Args:
        image: (H, W, 3) uint8 RGB.
        rule_names: the K rules.
        maps: (K, H, W) train ids of the rules (255: deferred).
        argmax: (H, W) train ids of argmax (the robotistic rule).
        defer_costs: per rule, its defer cost as text (``"0.3"``, ``"per class"``), or None for
            a rule that never defers; None: no rule defers.
        uncertainty: (H, W) maps in nats (``entropy``, and ``mutual_information`` with several
            runs; docs/definitions.md §13), or None: not drawn.
        segment_iou: per rule, (H, W) the predicted IoU of each pixel's segment (NaN: none) of
            meta models (docs/definitions.md §15), or None: not drawn.

    Returns:
        (h, w, 3) uint8 RGB, h and w even (video encoders need that): a top row with the image
        and the K overlays (a rule that defers: its defer cost and deferred share under its
        name), a bottom row with the entropy (its scale above it) and the K difference views,
        the mutual information below the entropy and each rule's segments by predicted IoU
        below its difference view, and a legend of the classes present (and of deferred pixels
        when a rule defers).
    """
    defer_costs = list(defer_costs or [None] * len(rule_names))
    h, w = _tile_size(*image.shape[:2])
    small = _resized(image, (h, w), nearest=False)
    k = len(rule_names)
    small_maps = [_resized(m.astype(np.uint8), (h, w), nearest=True) for m in maps]
    small_argmax = _resized(argmax.astype(np.uint8), (h, w), nearest=True)
    present = np.flatnonzero(np.bincount(np.concatenate([m.ravel() for m in small_maps]),
                                         minlength=256)[: len(CLASS_NAMES)])  # fmt: skip
    defers = any(c is not None for c in defer_costs)
    entries = [(CLASS_NAMES[c], colorize(np.array([c]))[0]) for c in present]
    entries += [("deferred", DEFERRED_COLOUR)] if defers else []
    title = 2 * TITLE - 4 if defers else TITLE
    width = (k + 1) * w + (k + 1) * w % 2
    legend_rows = -(-len(entries) // max(1, (width - 4) // 120))
    scales = uncertainty_tiles(uncertainty, len(CLASS_NAMES)) if uncertainty else []
    rows = 2 + (len(scales) > 1 or segment_iou is not None)
    height = rows * (h + title) + legend_rows * (SWATCH + 4) + 4
    canvas = Image.new("RGB", (width, height + height % 2), (255, 255, 255))
    draw, font = ImageDraw.Draw(canvas), ImageFont.load_default()
    tiles = [("image", small)] + [
        (_title(name, cost, m), overlay(small, sm))
        for name, cost, m, sm in zip(rule_names, defer_costs, maps, small_maps, strict=True)
    ]
    differ = [100 * float(np.count_nonzero(m != argmax)) / argmax.size for m in maps]
    coloured = [(t, _resized(t.rgb, (h, w), nearest=False)) for t in scales]
    tiles += coloured[:1] or [(None, None)]
    tiles += [
        (f"{name}: {d:.1f} % not argmax", differences(small, m, small_argmax))
        for name, m, d in zip(rule_names, small_maps, differ, strict=True)
    ]
    tiles += coloured[1:] or [(None, None)]
    if segment_iou is not None:
        for name, values in zip(rule_names, segment_iou, strict=True):
            tile = iou_tile(f"{name}: IoU (meta)", _resized_values(values, (h, w)))
            tiles.append((tile, tile.rgb))
    for i, (text, tile) in enumerate(tiles):
        if tile is None:
            continue
        x, y = (i % (k + 1)) * w, (i // (k + 1)) * (h + title)
        if isinstance(text, Tile):
            draw_title(draw, font, x + 3, y + 2, text)
        else:
            draw.text((x + 3, y + 2), text, fill=(0, 0, 0), font=font)
        canvas.paste(Image.fromarray(tile), (x, y + title))
    _legend(draw, font, entries, rows * (h + title) + 2, canvas.width)
    return np.asarray(canvas)


def deferred_percent(labels: np.ndarray) -> float:
    """The share of a label map's pixels that are deferred (255), in percent.

    >>> deferred_percent(np.array([[255, 0, 1, 255]]))
    50.0
    """
    return 100 * float(np.count_nonzero(labels == DEFERRED)) / labels.size


def _title(name: str, defer_cost: str | None, labels: np.ndarray) -> str:
    if defer_cost is None:
        return name
    return f"{name}\ndefer {defer_cost}: {deferred_percent(labels):.1f} % deferred"


def _legend(draw: ImageDraw.ImageDraw, font, entries, top: int, width: int) -> None:
    """Swatches of ``entries`` ((name, RGB) each), in rows of 120-pixel cells."""
    x, y = 4, top
    for name, rgb in entries:
        if x + 120 > width and x > 4:
            x, y = 4, y + SWATCH + 4
        fill = tuple(int(v) for v in rgb)
        draw.rectangle((x, y, x + SWATCH, y + SWATCH), fill=fill, outline=(0, 0, 0))
        draw.text((x + SWATCH + 4, y + 1), name, fill=(0, 0, 0), font=font)
        x += 120
