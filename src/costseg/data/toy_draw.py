"""Drawing helpers for the procedural street scenes of :mod:`costseg.data.toy`.

A pinhole camera looks along +Z over a flat ground (X to the right, Y up, metres). Each helper
draws one kind of object twice: crisp train ids on the label canvas and colours on the RGB canvas
(smoothed later, so image edges are anti-aliased while label edges stay sharp). Colours fade
towards the haze colour with distance, so far objects are genuinely harder to recognise.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from PIL import Image, ImageDraw

from costseg.classes import IGNORE_INDEX, class_indices

(ROAD, SIDEWALK, BUILDING, WALL, FENCE, POLE, LIGHT, SIGN, VEGETATION, TERRAIN, SKY, PERSON,
 RIDER, CAR, TRUCK, BUS, TRAIN, MOTORCYCLE, BICYCLE) = class_indices(
    ["road", "sidewalk", "building", "wall", "fence", "pole", "traffic light", "traffic sign",
     "vegetation", "terrain", "sky", "person", "rider", "car", "truck", "bus", "train",
     "motorcycle", "bicycle"])  # fmt: skip

RGB = tuple[int, int, int]
Point = tuple[float, float]
GLASS: RGB = (48, 58, 72)
TYRE: RGB = (22, 22, 24)
GREEN: RGB = (58, 100, 45)
# Clothes share greys and browns with poles, walls and buildings on purpose (partial ambiguity).
CLOTHES: tuple[RGB, ...] = (
    (35, 35, 40), (60, 65, 80), (120, 120, 125), (40, 60, 110), (150, 35, 40), (90, 60, 40),
    (50, 90, 60), (180, 120, 40), (110, 40, 110), (30, 100, 160), (200, 60, 60), (20, 20, 60),
)  # fmt: skip
HELMETS: tuple[RGB, ...] = ((235, 235, 235), (25, 25, 25), (200, 40, 40), (40, 70, 170))
# Riders mostly wear bright jackets (a learnable cue besides the two-wheeler under them).
JACKETS: tuple[RGB, ...] = (
    (230, 200, 30),
    (240, 120, 20),
    (30, 160, 200),
    (200, 30, 120),
    (35, 35, 40),
)
POLES: tuple[RGB, ...] = ((60, 65, 60), (45, 70, 55), (175, 180, 185))
WALLS: tuple[RGB, ...] = ((128, 138, 118), (185, 178, 125))  # mossy concrete, sandstone
SKIN: tuple[RGB, ...] = ((225, 185, 155), (180, 130, 95), (110, 75, 50))
FACADES: tuple[RGB, ...] = (
    (190, 170, 140), (140, 140, 140), (160, 85, 65), (215, 210, 200), (200, 170, 105),
    (110, 90, 75), (170, 160, 150), (120, 130, 140),
)  # fmt: skip
SIGNS: tuple[tuple[RGB, RGB], ...] = (
    ((30, 80, 200), (235, 235, 235)), ((205, 25, 30), (240, 240, 240)),
    ((245, 200, 0), (20, 20, 20)), ((240, 240, 240), (30, 110, 60)),
)  # fmt: skip
LAMPS: tuple[RGB, ...] = ((220, 30, 20), (235, 170, 20), (30, 210, 90))


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
    """An RGB image and its label, drawn together through one camera."""

    def __init__(
        self, image: Image.Image, label: Image.Image, cam: Camera, haze: RGB, haze_range: float
    ) -> None:
        self.image, self.label = ImageDraw.Draw(image), ImageDraw.Draw(label)
        self.cam, self.haze, self.haze_range = cam, haze, haze_range

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

    def line(self, pts: list[Point], cls: int | None, rgb: RGB, z: float, width: float) -> None:
        w = max(1, round(width))
        self.image.line(pts, fill=self.tint(rgb, z), width=w)
        if cls is not None:
            self.label.line(pts, fill=cls, width=w)

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


Span = tuple[float, float]


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


def chassis(cv: Canvas, xs: Span, zs: Span, side: float | None, r: float, cls: int) -> None:
    """Tyres: blocks under the front face, discs on the visible side face."""
    (x0, x1), (z0, z1) = xs, zs
    for xa, xb in ((x0 + 0.05, x0 + 0.3), (x1 - 0.3, x1 - 0.05)):
        cv.poly(cv.front(xa, xb, z0, 0.0, r), cls, TYRE, z0)
    if side is None:
        return
    ang = np.linspace(0, 2 * np.pi, 9)[:-1]
    for zc in (z0 + 2.5 * r, z1 - 2.5 * r):
        cv.poly([cv.cam.p(side, r + r * np.sin(a), zc + r * np.cos(a)) for a in ang], cls, TYRE, z0)


def car(cv: Canvas, rng: np.random.Generator, x: float, z: float, rgb: RGB, away: bool) -> None:
    """A car at lateral ``x`` with its near end at depth ``z`` (seen from behind when ``away``)."""
    w, length, top = rng.uniform(1.65, 1.95), rng.uniform(3.8, 4.8), rng.uniform(1.38, 1.55)
    xs, zs = (x - w / 2, x + w / 2), (z, z + length)
    cv.poly(cv.flat(xs[0] - 0.1, xs[1] + 0.1, z - 0.2, zs[1] + 0.1), None, (30, 30, 32), z)
    side = box(cv, xs, zs, (0.28, 0.92), CAR, rgb)
    cz = (z + length * (0.32 if away else 0.25), z + length * (0.8 if away else 0.7))
    cab = (xs[0] + 0.12, xs[1] - 0.12)
    cside = box(cv, cab, cz, (0.92, top), CAR, shade(rgb, 0.95))
    cv.poly(cv.front(cab[0] + 0.1, cab[1] - 0.1, cz[0], 0.97, top - 0.07), CAR, GLASS, z)
    if cside is not None:
        cv.poly(cv.side(cside, cz[0] + 0.1, cz[1] - 0.15, 0.97, top - 0.07), CAR, GLASS, z)
    lamp = (190, 25, 25) if away else (235, 230, 200)
    for xa in (xs[0] + 0.08, xs[1] - 0.38):
        cv.poly(cv.front(xa, xa + 0.3, z, 0.68, 0.82), CAR, lamp, z)
    chassis(cv, xs, zs, side, 0.32, CAR)


def truck(cv: Canvas, rng: np.random.Generator, x: float, z: float, rgb: RGB, away: bool) -> None:
    """A box truck: a tall cargo box and a lower cab (the cab in front when it comes our way)."""
    xs, lc, high = (x - 1.25, x + 1.25), rng.uniform(5.0, 8.0), rng.uniform(3.3, 3.9)
    cargo = jitter(rng, (int(rng.choice([235, 200, 150])),) * 3, 12)
    cv.poly(cv.flat(xs[0], xs[1], z - 0.2, z + lc + 2.4), None, (30, 30, 32), z)
    cab, load = ((z + lc + 0.2, z + lc + 2.4), (z, z + lc))
    if not away:
        cab, load = (z, z + 2.2), (z + 2.4, z + 2.4 + lc)
    # The far part first, so that the near one covers it.
    for zs, colour, top in sorted([(cab, rgb, 3.0), (load, cargo, high)], reverse=True):
        side = box(cv, xs, zs, (0.55, top), TRUCK, colour)
        if zs == cab:
            cv.poly(cv.front(xs[0] + 0.15, xs[1] - 0.15, zs[0], 1.7, 2.7), TRUCK, GLASS, z)
        else:  # the cargo doors' seam
            seam = [cv.cam.p(x, 0.6, zs[0]), cv.cam.p(x, top - 0.1, zs[0])]
            cv.line(seam, TRUCK, shade(colour, 0.6), zs[0], 0.05 * cv.cam.f / zs[0])
        chassis(cv, xs, zs, side, 0.5, TRUCK)


def bus(cv: Canvas, rng: np.random.Generator, x: float, z: float, rgb: RGB, away: bool) -> None:
    """A long bus with a row of side windows and a large windscreen."""
    xs, zs = (x - 1.27, x + 1.27), (z, z + rng.uniform(11.0, 13.5))
    cv.poly(cv.flat(xs[0], xs[1], z - 0.2, zs[1]), None, (30, 30, 32), z)
    side = box(cv, xs, zs, (0.3, 3.1), BUS, rgb)
    cv.poly(cv.front(xs[0] + 0.15, xs[1] - 0.15, z, 2.0 if away else 1.0, 2.8), BUS, GLASS, z)
    if side is not None:
        cv.poly(cv.side(side, z + 0.8, zs[1] - 0.5, 1.3, 2.6), BUS, GLASS, z)
        for zp in np.arange(z + 2.0, zs[1] - 1.0, 1.6):
            cv.poly(cv.side(side, zp, zp + 0.18, 1.3, 2.6), BUS, shade(rgb, 0.85), z)
    chassis(cv, xs, zs, side, 0.5, BUS)


def tram(cv: Canvas, rng: np.random.Generator, x: float, z: float, rgb: RGB) -> None:
    """A tram (train class) on its rails: very long, window band, red stripe, pantograph."""
    xs, zs = (x - 1.32, x + 1.32), (z, z + rng.uniform(20.0, 32.0))
    side = box(cv, xs, zs, (0.35, 3.4), TRAIN, rgb)
    stripe = jitter(rng, (170, 30, 35), 10)
    cv.poly(cv.front(xs[0], xs[1], z, 0.6, 0.95), TRAIN, stripe, z)
    cv.poly(cv.front(xs[0] + 0.2, xs[1] - 0.2, z, 1.3, 2.9), TRAIN, GLASS, z)
    if side is not None:
        cv.poly(cv.side(side, z + 0.5, zs[1], 0.6, 0.95), TRAIN, stripe, z)
        cv.poly(cv.side(side, z + 1.5, zs[1] - 0.5, 1.2, 2.5), TRAIN, GLASS, z)
    zp, p = z + 0.4 * (zs[1] - z), cv.cam.p
    pts = [p(x - 0.6, 3.4, zp), p(x, 4.6, zp), p(x + 0.6, 3.4, zp)]
    cv.line(pts, TRAIN, (40, 40, 40), zp, 0.07 * cv.cam.f / zp)


def figure(cv: Canvas, rng: np.random.Generator, foot: Point, h: float, cls: int, z: float,
           seated: bool = False) -> None:  # fmt: skip
    """A person ``h`` px tall whose feet (hips when ``seated``) are at pixel ``foot``."""
    (u, v), trousers = foot, pick(rng, CLOTHES, 10)
    shirt = pick(rng, JACKETS if cls == RIDER else CLOTHES, 10)
    hip, lean = (v, 0.12 * h) if seated else (v - 0.5 * h, 0.0)
    if seated:  # thigh forward, shin down to the pedal
        knee = (u + 0.2 * h, hip - 0.02 * h)
        cv.line([(u, hip), knee, (knee[0] - 0.03 * h, hip + 0.25 * h)], cls, trousers, z, 0.1 * h)
    else:
        step = rng.uniform(-0.12, 0.12) * h
        for dx, s in ((-0.1 * h, step), (0.0, -step)):
            leg = [
                (u + dx, hip),
                (u + dx + 0.1 * h, hip),
                (u + dx + s + 0.1 * h, v),
                (u + dx + s, v),
            ]
            cv.poly(leg, cls, trousers, z)
    top, wide = hip - 0.35 * h, rng.uniform(0.09, 0.14) * h
    cv.poly([(u - wide, hip), (u + wide, hip), (u + wide + lean, top), (u - wide + lean, top)],
            cls, shirt, z)  # fmt: skip
    swing = rng.uniform(-0.08, 0.08) * h
    for sx in (-1.0, 1.0):
        hand = (u + sx * (wide + 0.02 * h + swing) + 1.5 * lean, hip + 0.03 * h)
        cv.line([(u + sx * wide + lean, top + 0.03 * h), hand], cls, shirt, z, 0.065 * h)
    hx, r = u + lean, 0.075 * h
    cv.ellipse([hx - r, top - 2.2 * r, hx + r, top], cls, pick(rng, SKIN, 8), z)
    hair = (int(rng.choice([20, 60, 110, 170])),) * 3 if cls == PERSON else pick(rng, HELMETS, 5)
    cap = [(hx - r, top - 1.5 * r), (hx - r, top - 1.9 * r), (hx, top - 2.2 * r)]
    cv.poly([*cap, (hx + r, top - 1.9 * r), (hx + r, top - 1.5 * r)], cls, hair, z)


def two_wheeler(cv: Canvas, rng: np.random.Generator, x: float, z: float, motor: bool,
                rider: bool) -> None:  # fmt: skip
    """A bicycle or motorcycle seen from the side, foreshortened, optionally with its rider."""
    s, (u, v) = cv.cam.f / z, cv.cam.p(x, 0.0, z)
    k = rng.uniform(0.45, 1.0) * rng.choice([-1.0, 1.0])
    cls = MOTORCYCLE if motor else BICYCLE
    r, half = (0.36 if motor else 0.34) * s, (0.85 if motor else 0.52) * s * k
    hubs, ring = [(u - half, v - r), (u + half, v - r)], max(1, round(0.09 * s))
    seat = (u - 0.2 * half, v - (0.8 if motor else 0.9) * s)
    bar = (u + 0.8 * half, v - (1.0 if motor else 1.05) * s)
    for cx, cy in hubs:  # a bicycle's spoked wheel is labelled whole, like a disc
        wheel = [cx - r * abs(k), cy - r, cx + r * abs(k), cy + r]
        cv.ellipse(wheel, cls, TYRE if motor else (105, 105, 110), z)
        cv.ellipse(wheel, cls, TYRE, z, width=ring)
    body = pick(rng, CLOTHES)
    if motor:
        tank = [(u - 0.6 * half, seat[1]), (u + 0.5 * half, v - 0.88 * s), bar, hubs[1]]
        engine = [(u + 0.3 * half, v - 0.22 * s), (u - 0.3 * half, v - 0.25 * s)]
        cv.poly([hubs[0], *tank, *engine], cls, body, z)
    else:
        pedal = (u, v - 0.3 * s)
        cv.line([hubs[0], seat, pedal, hubs[0]], cls, body, z, 0.1 * s)
        cv.line([seat, bar, hubs[1], bar, pedal], cls, body, z, 0.1 * s)
    if rider:
        figure(cv, rng, seat, rng.uniform(1.6, 1.85) * s, RIDER, z, seated=True)


def pole(cv: Canvas, rng: np.random.Generator, x: float, z: float, kind: str, arm: float) -> None:
    """A pole carrying a traffic ``"sign"``, a traffic ``"light"`` or a street ``"lamp"``.

    ``arm`` is the signed length (m) of a horizontal arm over the road, 0 for none.
    """
    p, s, grey = cv.cam.p, cv.cam.f / z, pick(rng, POLES, 8)
    height = {"sign": rng.uniform(2.8, 3.8), "light": rng.uniform(3.2, 5.5), "lamp": 7.5}[kind]
    w = rng.uniform(0.24, 0.34)
    cv.poly(cv.front(x - w / 2, x + w / 2, z, 0.0, height), POLE, grey, z)
    cv.poly(cv.front(x - w / 2, x - w / 6, z, 0.0, height), None, shade(grey, 1.35), z)  # sheen
    if arm:
        cv.line([p(x, height - 0.1, z), p(x + arm, height - 0.1, z)], POLE, grey, z, w * s)
    if kind == "lamp":
        head = [*p(x + arm - 0.35, height + 0.1, z), *p(x + arm + 0.35, height - 0.3, z)]
        cv.ellipse(head, POLE, (60, 60, 60), z)
    elif kind == "sign":
        sign(cv, rng, x, height - rng.uniform(0.3, 0.5), z)
    else:
        cx, top = x + (arm or rng.choice([-1.0, 1.0]) * 0.3), height - (0.2 if arm else 1.5)
        cv.poly(cv.front(cx - 0.24, cx + 0.24, z - 0.05, top - 1.2, top), LIGHT, (28, 30, 28), z)
        lit = rng.integers(3)
        for i, lamp in enumerate(LAMPS):
            y = top - 0.22 - 0.38 * i
            disc = [*p(cx - 0.15, y + 0.15, z), *p(cx + 0.15, y - 0.15, z)]
            cv.ellipse(disc, LIGHT, lamp if i == lit else shade(lamp, 0.3), z)


def sign(cv: Canvas, rng: np.random.Generator, x: float, y: float, z: float) -> None:
    """A bright traffic-sign plate centred at (x, y, z): disc, triangle, diamond or panel."""
    a, (u, v) = rng.uniform(0.38, 0.52) * cv.cam.f / z, cv.cam.p(x, y, z)
    (base, inner), shape = SIGNS[rng.integers(len(SIGNS))], rng.integers(4)
    if shape == 0:
        cv.ellipse([u - a, v - a, u + a, v + a], SIGN, base, z)
        cv.ellipse([u - 0.6 * a, v - 0.6 * a, u + 0.6 * a, v + 0.6 * a], SIGN, inner, z)
        return
    outline = [
        [(-1.0, 0.8), (0.0, -1.0), (1.0, 0.8)],
        [(-1.0, 0.0), (0.0, -1.0), (1.0, 0.0), (0.0, 1.0)],
        [(-1.2, -0.7), (1.2, -0.7), (1.2, 0.7), (-1.2, 0.7)],
    ][shape - 1]
    cv.poly([(u + a * du, v + a * dv) for du, dv in outline], SIGN, base, z)
    cv.poly([(u + 0.55 * a * du, v + 0.55 * a * dv) for du, dv in outline], SIGN, inner, z)


def tree(cv: Canvas, rng: np.random.Generator, x: float, z: float, height: float) -> None:
    """A tree: trunk and a crown of overlapping blobs (all vegetation)."""
    p, s, r = cv.cam.p, cv.cam.f / z, 0.3 * height
    cv.poly(cv.front(x - 0.15, x + 0.15, z, 0.0, 0.6 * height), VEGETATION, (85, 68, 50), z)
    green = jitter(rng, GREEN, 12)
    for _ in range(int(rng.integers(4, 8))):
        u, v = p(x + rng.normal(0, 0.45 * r), height - r + rng.normal(0, 0.35 * r), z)
        rx, ry = rng.uniform(0.5, 0.85, 2) * r * s
        cv.ellipse([u - rx, v - ry, u + rx, v + ry], VEGETATION, jitter(rng, green, 10), z)


def clutter(cv: Canvas, rng: np.random.Generator, x: float, z: float) -> None:
    """Unlabelled street furniture (bins, boxes, advertising columns): ignore label."""
    w, h = rng.uniform(0.5, 1.2), rng.uniform(0.7, 2.5)
    colour = jitter(rng, (90, 90, 80), 40)
    box(cv, (x - w / 2, x + w / 2), (z, z + w), (0.0, h), IGNORE_INDEX, colour)


def green_wall(cv: Canvas, rng: np.random.Generator, x: float, zs: Span, height: float) -> None:
    """A tree line or hedge in the plane X = x with a bumpy top (vegetation)."""
    z = np.geomspace(zs[0], zs[1], int(np.clip((zs[1] - zs[0]) / 3, 3, 30)))
    top = height * rng.uniform(0.75, 1.2, len(z))
    crest = [cv.cam.p(x, y, zz) for y, zz in zip(top.tolist(), z.tolist(), strict=True)]
    pts = [cv.cam.p(x, 0.0, zs[0]), *crest, cv.cam.p(x, 0.0, zs[1])]
    cv.poly(pts, VEGETATION, jitter(rng, GREEN, 12), zs[0])


def building(cv: Canvas, rng: np.random.Generator, x: float, zs: Span, height: float) -> None:
    """A facade in the plane X = x with floors of windows and, sometimes, shop windows."""
    (z0, z1), cam = zs, cv.cam
    cv.poly(cv.side(x, z0, z1, 0.0, height), BUILDING, pick(rng, FACADES, 12), z0)
    glass = jitter(rng, (55, 65, 80))
    if rng.random() < 0.5:
        cv.poly(cv.side(x, z0 + 0.8, z1 - 0.8, 0.5, 2.6), None, glass, z0)
    floor, ww, wh, step = rng.uniform((2.9, 0.9, 1.2, 2.2), (3.5, 1.5, 1.8, 3.6)).tolist()
    for zc in np.arange(z0 + step / 2, z1 - ww, step).tolist():
        top = min(height - 1.0, cam.hc + cam.hy * zc / cam.f)  # higher rows are out of view
        for y in np.arange(floor + 0.8, top, floor).tolist():
            cv.poly(cv.side(x, zc, zc + ww, y, y + wh), None, glass, zc)


def barrier(cv: Canvas, rng: np.random.Generator, x: float, zs: Span, height: float,
            cls: int) -> None:  # fmt: skip
    """A block wall with a coping, or a board fence with posts and a rail, at X = x."""
    p, (z0, z1) = cv.cam.p, zs
    colour = pick(rng, WALLS if cls == WALL else ((95, 110, 95), (135, 105, 75)), 12)
    cv.poly(cv.side(x, z0, z1, 0.0, height), cls, colour, z0)
    dark = shade(colour, 0.6 if cls == FENCE else 1.2)
    cv.poly(cv.side(x, z0, z1, height * 0.9, height), cls, dark, z0)
    if cls == WALL:  # mortar joints between blocks
        joint = shade(colour, 0.7)
        for y in np.arange(0.4, 0.9 * height, 0.4).tolist():
            cv.line([p(x, y, z0), p(x, y, z1)], None, joint, z0, 1)
        for z in np.arange(z0 + 1.0, z1, 1.0).tolist():
            cv.line([p(x, 0.0, z), p(x, 0.9 * height, z)], None, joint, z, 1)
        return
    for z in np.arange(z0, z1, rng.uniform(1.5, 3.0)).tolist():
        cv.line([p(x, 0.0, z), p(x, height, z)], cls, dark, z, 0.08 * cv.cam.f / z)
    cv.line([p(x, height * 0.45, z0), p(x, height * 0.45, z1)], cls, dark, z0, 1)
