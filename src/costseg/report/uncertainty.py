"""Uncertainty maps as pictures (``docs/definitions.md §13``): the predictive entropy and, with
several runs, the mutual information, in the colours of matplotlib's ``inferno`` (black: 0,
pale yellow: the top of the scale). The entropy's scale is fixed, 0 to log N (N classes: the
most uncertain map); the mutual information's runs from 0 to its largest value in the image
(it is usually far below log N). Every tile states its scale: the name, 0, a colour bar and
the top, in nats. The segments' predicted IoU of meta models (docs/definitions.md §15) are tiles
too, in ``IOU_COLOURS`` from 0 to 1.

>>> maps = {"entropy": np.full((4, 6), 0.5), "mutual_information": np.zeros((4, 6))}
>>> [(t.name, round(t.top, 3), t.rgb.shape) for t in uncertainty_tiles(maps, 19)]
[('entropy', 2.944, (4, 6, 3)), ('mutual information', 2.944, (4, 6, 3))]
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from functools import cache

import numpy as np
from PIL import Image, ImageDraw, ImageFont

SHOWN = {"entropy": "entropy", "mutual_information": "mutual information"}
"""The maps drawn (keys of the uncertainty maps) and their titles, in this order."""
IOU_COLOURS = "RdYlGn"  # a segment's IoU: red 0 (a false segment), green 1
NO_SEGMENT = (128, 128, 128)  # pixels of no segment in an IoU tile
TITLE = 16  # pixels above each tile of a strip
BAR = (40, 8)  # (width, height) of the colour bar in a tile's title


@dataclass
class Tile:
    """One map in colour: its title, the top of its scale, (H, W, 3) RGB, the colour map and the
    unit of its scale."""

    name: str
    top: float
    rgb: np.ndarray
    colours: str = "inferno"
    unit: str = "nats"

    @property
    def scale(self) -> str:
        """The title and scale, two lines: e.g. ``entropy, nats`` and ``0 black … 2.94 yellow``."""
        return f"{self.name}, nats\n0 black … {self.top:.3g} yellow"


@cache
def _palette(colours: str = "inferno") -> np.ndarray:
    """(256, 3) uint8: a matplotlib colour map (``inferno``: black to pale yellow)."""
    from matplotlib import colormaps

    return (colormaps[colours](np.linspace(0, 1, 256))[:, :3] * 255).round().astype(np.uint8)


def coloured(values: np.ndarray, top: float, colours: str = "inferno") -> np.ndarray:
    """(H, W) values → (H, W, 3) uint8 RGB of the colour map, 0 its first colour, ``top`` and
    above its last (``inferno``: black, pale yellow).

    >>> coloured(np.array([[0.0, 1.0, 2.0]]), 1.0)[0].tolist()
    [[0, 0, 4], [252, 255, 164], [252, 255, 164]]
    """
    scaled = np.clip(np.nan_to_num(np.asarray(values, np.float64) / top) * 255, 0, 255)
    return _palette(colours)[(scaled + 0.5).astype(np.intp)]


def iou_tile(name: str, values: np.ndarray) -> Tile:
    """(H, W) IoU of each pixel's segment (NaN: no segment) as a tile: ``IOU_COLOURS`` from 0
    to 1, ``NO_SEGMENT`` grey off the segments.

    >>> iou_tile("ml", np.array([[0.0, np.nan]])).rgb[0].tolist()
    [[165, 0, 38], [128, 128, 128]]
    """
    rgb = coloured(values, 1.0, IOU_COLOURS)
    rgb[np.isnan(values)] = NO_SEGMENT
    return Tile(name, 1.0, rgb, IOU_COLOURS, "")


def uncertainty_tiles(maps: Mapping[str, np.ndarray], num_classes: int) -> list[Tile]:
    """The drawn maps among ``maps`` (name → (H, W) nats), each coloured on its scale: the
    entropy 0 … log N, the mutual information 0 … its largest value (log N where all are 0)."""
    tiles = []
    for key, name in SHOWN.items():
        if key not in maps:
            continue
        values = np.asarray(maps[key], np.float32)
        top = math.log(num_classes)
        if key != "entropy":
            top = float(values.max(initial=0.0)) or top
        tiles.append(Tile(name, top, coloured(values, top)))
    return tiles


def draw_title(draw: ImageDraw.ImageDraw, font, x: int, y: int, tile: Tile) -> None:
    """``name 0 ▭ top unit`` at (x, y): the tile's scale with its colour bar."""
    text = f"{tile.name} 0"
    draw.text((x, y), text, fill=(0, 0, 0), font=font)
    left = x + int(draw.textlength(text, font=font)) + 3
    for i in range(BAR[0]):
        colour = tuple(int(c) for c in _palette(tile.colours)[i * 255 // (BAR[0] - 1)])
        draw.line((left + i, y + 2, left + i, y + 1 + BAR[1]), fill=colour)
    top = f"{tile.top:.3g} {tile.unit}".rstrip()
    draw.text((left + BAR[0] + 3, y), top, fill=(0, 0, 0), font=font)


def uncertainty_strip(maps: Mapping[str, np.ndarray], num_classes: int) -> np.ndarray:
    """The drawn maps side by side, each under its scale (for TensorBoard): (16 + H, k W, 3)
    uint8 RGB.

    >>> uncertainty_strip({"entropy": np.zeros((5, 200))}, 19).shape
    (21, 200, 3)
    """
    tiles = uncertainty_tiles(maps, num_classes)
    height, width = tiles[0].rgb.shape[:2]
    canvas = Image.new("RGB", (width * len(tiles), height + TITLE), (255, 255, 255))
    draw, font = ImageDraw.Draw(canvas), ImageFont.load_default()
    for i, tile in enumerate(tiles):
        draw_title(draw, font, i * width + 3, 2, tile)
        canvas.paste(Image.fromarray(tile.rgb), (i * width, TITLE))
    return np.asarray(canvas)
