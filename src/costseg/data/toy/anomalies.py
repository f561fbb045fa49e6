"""Unknown objects in the procedural street scenes (docs/definitions.md §17): things of no
Cityscapes class (lost cargo, animals, debris) on the road and beside it.

They are drawn after everything else, with the ignore label (255: no class is right) and, on a
mask of their own, 1: the SegmentMeIfYouCan anomaly mask is 1 on them, 255 on the scene's other
ignored pixels and 0 on every known class.
"""

from __future__ import annotations

import numpy as np
from PIL import ImageDraw

from costseg.classes import IGNORE_INDEX
from costseg.data.toy.draw import RGB, Canvas, Point, box, jitter, pick
from costseg.data.toy.street import Street

CARGO = ((160, 120, 75), (40, 80, 160), (220, 120, 30), (130, 90, 50), (200, 200, 190))
FUR = ((120, 85, 55), (90, 90, 85), (190, 170, 140), (40, 35, 30))
DEBRIS = ((35, 35, 38), (110, 105, 95), (150, 60, 40))


class MarkedCanvas:
    """``canvas``, drawing with the ignore label and marking every pixel drawn on ``mask``."""

    def __init__(self, canvas: Canvas, mask: ImageDraw.ImageDraw) -> None:
        self.canvas, self.mask = canvas, mask

    def __getattr__(self, name: str):
        return getattr(self.canvas, name)  # the camera, the quads of planes, the tint

    def poly(self, pts: list[Point], cls: int | None, rgb: RGB, z: float) -> None:
        self.canvas.poly(pts, IGNORE_INDEX, rgb, z)
        self.mask.polygon(pts, fill=1)

    def ellipse(self, bounds: list[float], cls: int, rgb: RGB, z: float) -> None:
        bounds = [bounds[0], bounds[1], max(bounds[0], bounds[2]), max(bounds[1], bounds[3])]
        self.canvas.ellipse(bounds, IGNORE_INDEX, rgb, z)
        self.mask.ellipse(bounds, fill=1)

    def line(self, pts: list[Point], cls: int | None, rgb: RGB, z: float, width: float) -> None:
        self.canvas.line(pts, IGNORE_INDEX, rgb, z, width)
        self.mask.line(pts, fill=1, width=max(1, round(width)))


def cargo(cv: MarkedCanvas, rng: np.random.Generator, x: float, z: float) -> None:
    """A lost box, crate or barrel-sized block."""
    w, d, h = rng.uniform((0.3, 0.3, 0.25), (0.9, 0.8, 0.7)).tolist()
    box(cv, (x - w / 2, x + w / 2), (z, z + d), (0.0, h), IGNORE_INDEX, pick(rng, CARGO, 20))


def animal(cv: MarkedCanvas, rng: np.random.Generator, x: float, z: float) -> None:
    """A four-legged animal seen from the side: body, head, legs."""
    length, height = rng.uniform(0.6, 1.3), rng.uniform(0.45, 0.9)
    fur, p, facing = pick(rng, FUR, 12), cv.cam.p, 1.0 if rng.random() < 0.5 else -1.0
    legs = height * 0.55
    for dx in (-0.35, -0.25, 0.25, 0.35):
        top, foot = p(x + dx * length, legs + 0.05, z), p(x + dx * length, 0.0, z)
        cv.line([top, foot], None, jitter(rng, fur, 6), z, max(1.0, 0.08 * cv.cam.f / z))
    (x0, y0), (x1, y1) = p(x - length / 2, height, z), p(x + length / 2, legs, z)
    cv.ellipse([x0, y0, x1, y1], IGNORE_INDEX, fur, z)
    head = x + facing * length * 0.55
    (hx0, hy0), (hx1, hy1) = p(head - 0.14, height * 1.15, z), p(head + 0.14, height * 0.8, z)
    cv.ellipse([hx0, hy0, hx1, hy1], IGNORE_INDEX, jitter(rng, fur, 10), z)


def debris(cv: MarkedCanvas, rng: np.random.Generator, x: float, z: float) -> None:
    """An irregular flat piece lying on the ground (a torn tyre, rubble, a lost tarpaulin)."""
    radius, corners = rng.uniform(0.3, 1.0), int(rng.integers(5, 9))
    angles = np.sort(rng.uniform(0, 2 * np.pi, corners))
    reach = radius * rng.uniform(0.5, 1.0, corners)
    pts = [
        cv.cam.p(x + r * np.cos(a), 0.05, z + r * np.sin(a))
        for a, r in zip(angles, reach, strict=True)
    ]
    cv.poly(pts, IGNORE_INDEX, pick(rng, DEBRIS, 15), z)


KINDS = (cargo, animal, debris)


def draw_anomalies(
    cv: Canvas, rng: np.random.Generator, st: Street, mask: ImageDraw.ImageDraw
) -> None:
    """One to three unknown objects: the first on the road ahead, each other one on the road
    (three in four) or beside it."""
    marked, placed = MarkedCanvas(cv, mask), []
    for k in range(int(rng.integers(1, 4))):
        z = float(np.exp(rng.uniform(np.log(6.0), np.log(30.0))))
        if k == 0:  # ahead, in view
            x = np.clip(rng.normal(0.0, 1.2), st.edges[0] + 0.6, st.edges[1] - 0.6)
        elif rng.random() < 0.75:
            x = rng.uniform(st.edges[0] + 0.6, st.edges[1] - 0.6)
        else:  # on a sidewalk, between the curb and its outer edge
            side = int(rng.integers(2))
            x = rng.uniform(*sorted((st.edges[side], st.outer[side])))
        placed.append((z, float(x), KINDS[int(rng.integers(len(KINDS)))]))
    for z, x, kind in sorted(placed, key=lambda item: -item[0]):  # far to near
        kind(marked, rng, x, z)
