"""Street furniture and buildings of the procedural street scenes.

Poles with traffic signs, traffic lights or lamps; trees, hedges and tree lines; facades with
windows; walls and fences; unlabelled clutter. All are drawn on a
:class:`~costseg.data.toy.draw.Canvas` in world coordinates (metres).
"""

from __future__ import annotations

import numpy as np

from costseg.classes import IGNORE_INDEX
from costseg.data.toy.draw import (
    BUILDING,
    FENCE,
    LIGHT,
    POLE,
    RGB,
    SIGN,
    VEGETATION,
    WALL,
    Canvas,
    Span,
    box,
    jitter,
    pick,
    shade,
)

GREEN: RGB = (58, 100, 45)
POLES: tuple[RGB, ...] = ((60, 65, 60), (45, 70, 55), (175, 180, 185))
WALLS: tuple[RGB, ...] = ((128, 138, 118), (185, 178, 125))  # mossy concrete, sandstone
FACADES: tuple[RGB, ...] = (
    (190, 170, 140), (140, 140, 140), (160, 85, 65), (215, 210, 200), (200, 170, 105),
    (110, 90, 75), (170, 160, 150), (120, 130, 140),
)  # fmt: skip
SIGNS: tuple[tuple[RGB, RGB], ...] = (
    ((30, 80, 200), (235, 235, 235)), ((205, 25, 30), (240, 240, 240)),
    ((245, 200, 0), (20, 20, 20)), ((240, 240, 240), (30, 110, 60)),
)  # fmt: skip
LAMPS: tuple[RGB, ...] = ((220, 30, 20), (235, 170, 20), (30, 210, 90))


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
