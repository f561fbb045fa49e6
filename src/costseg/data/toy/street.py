"""Street layout of the procedural street scenes and its fixed parts.

:class:`Street` samples one scene's camera, road, lanes, sidewalks, facades and sky; the
``draw_*`` functions paint the buildings at the back and along both sides, the ground with its
markings, and the walls, fences and hedges along the sidewalks.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from PIL import Image

from costseg.classes import IGNORE_INDEX
from costseg.data.toy.draw import (
    BUILDING,
    FENCE,
    RGB,
    ROAD,
    SIDEWALK,
    TERRAIN,
    VEGETATION,
    WALL,
    Camera,
    Canvas,
    jitter,
    pick,
    shade,
)
from costseg.data.toy.scenery import FACADES, GREEN, barrier, building, green_wall


@dataclass(frozen=True)
class Street:
    """One scene's layout: camera, X (m) of the road edges, sidewalks' outer edges and facades."""

    cam: Camera
    edges: tuple[float, float]
    outer: tuple[float, float]
    facades: tuple[float, float]
    park: tuple[bool, bool]
    lanes: tuple[float, ...]  # lane centres; lanes before ``oncoming`` come towards the camera
    oncoming: int
    end: float  # depth where the street ends in a cross row of buildings
    sky: tuple[RGB, RGB]  # zenith and horizon (= haze) colours
    haze_range: float

    @classmethod
    def sample(cls, rng: np.random.Generator, h: int, w: int) -> Street:
        f, cx, hy, hc = rng.uniform(
            (0.9 * w, 0.46 * w, 0.38 * h, 1.3), (1.1 * w, 0.54 * w, 0.46 * h, 1.7)
        )
        n, lw = int(rng.choice([2, 3, 4], p=[0.7, 0.2, 0.1])), rng.uniform(2.9, 3.5)
        oncoming = n // 2 if rng.random() < 0.7 else 0  # else a one-way street
        # The camera drives in a lane of its direction: on two-way streets mostly the one next
        # to the centre line, on one-way streets mostly a middle one.
        middle = oncoming if oncoming else (n - 1) // 2
        ego = middle if rng.random() < 0.8 else int(rng.integers(oncoming, n))
        lanes = tuple((k - ego) * lw for k in range(n))
        parking = np.where(rng.random(2) < 0.35, rng.uniform(2.0, 2.5, 2), 0.0)
        edges = (lanes[0] - lw / 2 - parking[0], lanes[-1] + lw / 2 + parking[1])
        walk, park = rng.uniform(4.5, 8.0, 2), rng.random(2) < 0.25
        verge = np.where(rng.random(2) < 0.75, rng.uniform(3.0, 9.0, 2), 0.0)  # front gardens
        verge += park * rng.uniform(3.0, 12.0, 2)
        outer = (edges[0] - walk[0], edges[1] + walk[1])
        facades = (outer[0] - verge[0], outer[1] + verge[1])
        clear = rng.random() < 0.6
        sky = ((70, 130, 200), (190, 210, 230)) if clear else ((165, 170, 180), (215, 215, 220))
        return cls(
            Camera(f, cx, hy, hc),
            edges,
            outer,
            facades,
            (bool(park[0]), bool(park[1])),
            lanes,
            oncoming,
            rng.uniform(60.0, 180.0),
            (jitter(rng, sky[0], 10), jitter(rng, sky[1], 8)),
            rng.uniform(120.0, 500.0),
        )

    def sky_gradient(self, h: int, w: int) -> Image.Image:
        """(W, H) RGB sky, deeper at the top, paler at the horizon."""
        t = np.clip(np.arange(h) / self.cam.hy, 0.0, 1.0)[:, None]
        rows = ((1.0 - t) * np.asarray(self.sky[0]) + t * np.asarray(self.sky[1])).astype(np.uint8)
        return Image.fromarray(rows[:, None, :]).resize((w, h), Image.NEAREST)


def draw_backdrop(cv: Canvas, rng: np.random.Generator, st: Street) -> None:
    """The cross row at the street's end, then the facades (or park tree lines) of both sides."""
    x = st.facades[0]
    while x < st.facades[1]:
        x1, height = min(st.facades[1], x + rng.uniform(5.0, 25.0)), rng.uniform(8.0, 28.0)
        cls, colour = (
            (BUILDING, pick(rng, FACADES))
            if rng.random() < 0.7
            else (VEGETATION, jitter(rng, GREEN))
        )
        cv.poly(cv.front(x, x1, st.end, 0.0, height), cls, colour, st.end)
        x = x1
    for x, park in zip(st.facades, st.park, strict=True):
        z = 1.0
        while z < st.end:
            zs = (z, st.end if park else min(st.end, z + rng.uniform(8.0, 30.0)))
            if park or rng.random() < 0.12:
                green_wall(cv, rng, x, zs, rng.uniform(7.0, 15.0))
            else:
                building(cv, rng, x, zs, rng.uniform(14.0, 34.0))
            z = zs[1]


def draw_ground(cv: Canvas, rng: np.random.Generator, st: Street) -> None:
    """Terrain, paved sidewalks with curbs and the road."""
    p, z0, z1 = cv.cam.p, 1.0, st.end
    for e, o, f in zip(st.edges, st.outer, st.facades, strict=True):
        if o != f:
            cv.poly(cv.flat(o, f, z0, z1), TERRAIN, jitter(rng, (125, 140, 65)), z0)
        walk = jitter(rng, (150, 140, 130), 14)
        cv.poly(cv.flat(e, o, z0, z1), SIDEWALK, walk, z0)
        for z in np.arange(rng.uniform(1.0, 3.0), 40.0, rng.uniform(1.2, 2.5)).tolist():
            cv.line([p(e, 0.0, z), p(o, 0.0, z)], None, shade(walk, 0.8), z, 1)
        if abs(o - e) > 4.0 and rng.random() < 0.35:  # a grass strip along the curb
            grass = (e + 0.3 * np.sign(o - e), e + rng.uniform(1.2, 2.2) * np.sign(o - e))
            cv.poly(cv.flat(*grass, z0, z1), TERRAIN, jitter(rng, (125, 140, 65)), z0)
        cv.poly(cv.side(e, z0, z1, 0.0, 0.15), SIDEWALK, shade(walk, 1.15), z0)
    cv.poly(cv.flat(*st.edges, z0, z1), ROAD, jitter(rng, (90, 90, 92), 12), z0)


def draw_markings(cv: Canvas, rng: np.random.Generator, st: Street) -> float | None:
    """Lane lines, maybe a zebra crossing and tram rails; returns the rails' X, if any."""
    paint, lw = jitter(rng, (215, 215, 210), 12), st.lanes[1] - st.lanes[0]
    far = min(st.end, 0.3 * cv.cam.f)  # beyond, lines are thinner than a pixel
    for k in range(1, len(st.lanes)):
        b = st.lanes[k] - lw / 2
        dashes = np.arange(rng.uniform(1.0, 9.0), far, 9.0).tolist()
        for za, zb in [(1.0, far)] if k == st.oncoming else [(z, z + 3.0) for z in dashes]:
            cv.poly(cv.flat(b - 0.07, b + 0.07, za, zb), None, paint, za)
    if rng.random() < 0.25:
        zc = rng.uniform(7.0, 25.0)
        for x in np.arange(st.edges[0] + 0.5, st.edges[1] - 0.5, 1.0).tolist():
            cv.poly(cv.flat(x, x + 0.5, zc, zc + 3.0), None, paint, zc)
    if rng.random() > 0.25:
        return None
    rail = st.lanes[st.oncoming]
    for x in (rail - 0.72, rail + 0.72):  # rail tracks are void in Cityscapes
        cv.poly(cv.flat(x - 0.04, x + 0.04, 1.0, min(st.end, 60.0)), IGNORE_INDEX, (150,) * 3, 1.0)
    return rail


def draw_edges(cv: Canvas, rng: np.random.Generator, st: Street) -> None:
    """Walls, fences and hedges along the outer edges of the sidewalks."""
    for o, f in zip(st.outer, st.facades, strict=True):
        x = o if o != f else 0.99 * f
        for cls, chance in ((WALL, 0.45), (FENCE, 0.4), (VEGETATION, 0.3)):
            if rng.random() < chance:
                z0 = rng.uniform(2.0, 30.0)
                zs = (z0, min(st.end, z0 + rng.uniform(5.0, 40.0)))
                if cls == VEGETATION:
                    green_wall(cv, rng, x, zs, rng.uniform(0.8, 2.0))
                else:
                    barrier(cv, rng, x, zs, rng.uniform(1.0, 2.6), cls)
