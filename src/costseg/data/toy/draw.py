"""Drawing primitives of the procedural street scenes (:mod:`costseg.data.toy.dataset`).

Train ids, colour helpers, a pinhole camera, a two-layer canvas and boxes. The camera looks along
+Z over a flat ground (X to the right, Y up, metres). Every shape is drawn twice: crisp train ids
on the label canvas and colours on the RGB canvas (smoothed later, so image edges are anti-aliased
while label edges stay sharp). Colours fade towards the haze colour with distance, so far objects
are genuinely harder to recognise. The objects themselves are in :mod:`costseg.data.toy.traffic`
and :mod:`costseg.data.toy.scenery`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from PIL import Image, ImageDraw

from costseg.classes import class_indices
from costseg.data.toy.instances import InstanceLayer

(ROAD, SIDEWALK, BUILDING, WALL, FENCE, POLE, LIGHT, SIGN, VEGETATION, TERRAIN, SKY, PERSON,
 RIDER, CAR, TRUCK, BUS, TRAIN, MOTORCYCLE, BICYCLE) = class_indices(
    ["road", "sidewalk", "building", "wall", "fence", "pole", "traffic light", "traffic sign",
     "vegetation", "terrain", "sky", "person", "rider", "car", "truck", "bus", "train",
     "motorcycle", "bicycle"])  # fmt: skip

RGB = tuple[int, int, int]
Point = tuple[float, float]
Span = tuple[float, float]


def pick(rng: np.random.Generator, colours: tuple[RGB, ...], amount: float = 15.0) -> RGB:
    """One of ``colours``, varied a little (per-object colour variation)."""
    return jitter(rng, colours[rng.integers(len(colours))], amount)


def jitter(rng: np.random.Generator, rgb: RGB, amount: float = 15.0) -> RGB:
    """A colour near ``rgb``: mostly lighter or darker, its hue only slightly shifted."""
    light, *tone = rng.normal(0.0, amount, 4).tolist()
    r, g, b = (int(c + light + t / 3) for c, t in zip(rgb, tone, strict=True))
    return (min(255, max(0, r)), min(255, max(0, g)), min(255, max(0, b)))


def shade(rgb: RGB, k: float) -> RGB:
    """``rgb`` darkened (k < 1) or brightened (k > 1)."""
    return (min(255, int(rgb[0] * k)), min(255, int(rgb[1] * k)), min(255, int(rgb[2] * k)))


@dataclass(frozen=True)
class Camera:
    """Pinhole camera: focal length ``f`` (px), vanishing point (cx, hy) (px), height hc (m)."""

    f: float
    cx: float
    hy: float
    hc: float

    def p(self, x: float, y: float, z: float) -> Point:
        """Image position of the world point (x, y, z)."""
        return (self.cx + self.f * x / z, self.hy + self.f * (self.hc - y) / z)


class Canvas:
    """An RGB image and its label (and optionally instance ids), drawn together through one
    camera."""

    def __init__(
        self,
        image: Image.Image,
        label: Image.Image,
        cam: Camera,
        haze: RGB,
        haze_range: float,
        instances: InstanceLayer | None = None,
    ) -> None:
        self.image, self.label = ImageDraw.Draw(image), ImageDraw.Draw(label)
        self.cam, self.haze, self.haze_range = cam, haze, haze_range
        self.instances = instances

    def begin_object(self) -> None:
        """The shapes drawn from here on belong to a new object (a new instance per class)."""
        if self.instances is not None:
            self.instances.begin_object()

    def tint(self, rgb: RGB, z: float) -> RGB:
        t = (z - 10.0) / self.haze_range
        if t <= 0.0:
            return rgb
        t, (hr, hg, hb) = min(t, 0.6), self.haze
        r, g, b = rgb
        return (int(r + (hr - r) * t), int(g + (hg - g) * t), int(b + (hb - b) * t))

    def poly(self, pts: list[Point], cls: int | None, rgb: RGB, z: float) -> None:
        """Fill a polygon; ``cls=None`` paints the image only (texture, markings, shadows)."""
        self.image.polygon(pts, fill=self.tint(rgb, z))
        if cls is not None:
            self.label.polygon(pts, fill=cls)
            if self.instances is not None:
                self.instances.draw.polygon(pts, fill=self.instances.value(cls))

    def ellipse(self, box: list[float], cls: int, rgb: RGB, z: float, width: int = 0) -> None:
        """An ellipse in its bounding box (x0, y0, x1, y1); a ring when ``width`` > 0."""
        box = [box[0], box[1], max(box[0], box[2]), max(box[1], box[3])]
        colour = self.tint(rgb, z)
        if width:
            self.image.ellipse(box, outline=colour, width=width)
            self.label.ellipse(box, outline=cls, width=width)
        else:
            self.image.ellipse(box, fill=colour)
            self.label.ellipse(box, fill=cls)
        if self.instances is not None:
            value = self.instances.value(cls)
            kind = {"outline": value, "width": width} if width else {"fill": value}
            self.instances.draw.ellipse(box, **kind)

    def line(self, pts: list[Point], cls: int | None, rgb: RGB, z: float, width: float) -> None:
        w = max(1, round(width))
        self.image.line(pts, fill=self.tint(rgb, z), width=w)
        if cls is not None:
            self.label.line(pts, fill=cls, width=w)
            if self.instances is not None:
                self.instances.draw.line(pts, fill=self.instances.value(cls), width=w)

    def side(self, x: float, z0: float, z1: float, y0: float, y1: float) -> list[Point]:
        """Quad in the plane X = x (facades, vehicle sides)."""
        p = self.cam.p
        return [p(x, y0, z0), p(x, y1, z0), p(x, y1, z1), p(x, y0, z1)]

    def front(self, x0: float, x1: float, z: float, y0: float, y1: float) -> list[Point]:
        """Quad in the plane Z = z (faces seen head-on)."""
        p = self.cam.p
        return [p(x0, y0, z), p(x0, y1, z), p(x1, y1, z), p(x1, y0, z)]

    def flat(self, x0: float, x1: float, z0: float, z1: float, y: float = 0.0) -> list[Point]:
        """Quad in the plane Y = y (ground, roofs)."""
        p = self.cam.p
        return [p(x0, y, z0), p(x1, y, z0), p(x1, y, z1), p(x0, y, z1)]


def box(cv: Canvas, xs: Span, zs: Span, ys: Span, cls: int, rgb: RGB) -> float | None:
    """Visible faces of an axis-aligned box; returns the X of its visible side face, if any."""
    (x0, x1), (z0, z1), (y0, y1) = xs, zs, ys
    side = x1 if x1 < 0 else x0 if x0 > 0 else None
    if side is not None:
        cv.poly(cv.side(side, z0, z1, y0, y1), cls, shade(rgb, 0.8), z0)
    if y1 < cv.cam.hc:
        cv.poly(cv.flat(x0, x1, z0, z1, y1), cls, shade(rgb, 1.12), z0)
    cv.poly(cv.front(x0, x1, z0, y0, y1), cls, rgb, z0)
    return side
