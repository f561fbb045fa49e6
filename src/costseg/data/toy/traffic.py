"""Road users of the procedural street scenes: cars, trucks, buses, trams, persons and riders.

Each drawing function takes the :class:`~costseg.data.toy.draw.Canvas` and the scene's generator,
places its object in world coordinates (metres) and paints it on image and label alike.
"""

from __future__ import annotations

import numpy as np

from costseg.data.toy.draw import (
    BICYCLE,
    BUS,
    CAR,
    MOTORCYCLE,
    PERSON,
    RGB,
    RIDER,
    TRAIN,
    TRUCK,
    Canvas,
    Point,
    Span,
    box,
    jitter,
    pick,
    shade,
)

GLASS: RGB = (48, 58, 72)
TYRE: RGB = (22, 22, 24)
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
SKIN: tuple[RGB, ...] = ((225, 185, 155), (180, 130, 95), (110, 75, 50))
CAR_PAINT: tuple[RGB, ...] = (
    (190, 190, 195), (30, 30, 35), (225, 225, 225), (150, 25, 30), (30, 55, 120), (80, 80, 85),
    (40, 75, 55), (120, 110, 90),
)  # fmt: skip
BUS_PAINT: tuple[RGB, ...] = ((235, 190, 30), (200, 40, 40), (230, 120, 30), (40, 90, 170))
TRAM_PAINT: tuple[RGB, ...] = ((235, 235, 225), (215, 225, 200), (200, 215, 225))


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


def pedestrian(cv: Canvas, rng: np.random.Generator, x: float, z: float, tall: float) -> None:
    """A standing person ``tall`` metres tall with its feet at (x, 0, z)."""
    figure(cv, rng, cv.cam.p(x, 0.0, z), tall * cv.cam.f / z, PERSON, z)
