"""Scene composition of the procedural street scenes: what stands where, drawn far to near.

:func:`draw_street` paints a sampled :class:`~costseg.data.toy.street.Street`: its fixed parts,
then poles, trees, pedestrians, parked two-wheelers, vehicles and riders, and finally cast
shadows and maybe the ego vehicle's hood.
"""

from __future__ import annotations

from collections.abc import Callable
from functools import partial

import numpy as np
from PIL import ImageDraw

from costseg.classes import IGNORE_INDEX
from costseg.data.toy.draw import FENCE, Canvas, Span, pick
from costseg.data.toy.scenery import barrier, clutter, pole, sign, tree
from costseg.data.toy.street import Street, draw_backdrop, draw_edges, draw_ground, draw_markings
from costseg.data.toy.traffic import (
    BUS_PAINT,
    CAR_PAINT,
    TRAM_PAINT,
    bus,
    car,
    pedestrian,
    tram,
    truck,
    two_wheeler,
)


def _loguniform(rng: np.random.Generator, lo: float, hi: float) -> float:
    # Depths: as many objects between 5 and 10 m as between 30 and 60 m.
    return float(np.exp(rng.uniform(np.log(lo), np.log(hi))))


class _Queue:
    """Drawings made far to near: sorted by (layer, -depth, order of queueing).

    Layer 0 stands on a sidewalk, 1 is a railing at the curb, 2 stands at the curb or on the road
    (so it covers the sidewalk behind it).
    """

    def __init__(self, cv: Canvas, rng: np.random.Generator) -> None:
        self.cv, self.rng = cv, rng
        self.items: list[tuple[int, float, int, Callable[[], None]]] = []

    def add(self, layer: int, z: float, fn: Callable[..., None], *args: object) -> None:
        self.items.append((layer, -z, len(self.items), partial(fn, self.cv, self.rng, *args)))

    def draw(self) -> None:
        for *_, draw in sorted(self.items, key=lambda item: item[:3]):
            self.cv.begin_object()  # each queued drawing is one object (one instance per class)
            draw()


def _poles_and_trees(q: _Queue, st: Street, side: int) -> None:
    """Poles with signs, lights or lamps along one curb, and maybe a row of trees."""
    rng, e, out = q.rng, st.edges[side], 1.0 if side else -1.0  # out: away from the road
    z = rng.uniform(3.0, 15.0)
    while z < min(st.end - 5.0, 80.0):
        kind = str(rng.choice(["sign", "light", "lamp"], p=[0.4, 0.35, 0.25]))
        arm = {"sign": 0.0, "light": rng.uniform(2.0, 5.0), "lamp": 1.5}[kind]
        q.add(2, z, pole, e + out * 0.5, z, kind, -out * arm * (rng.random() < 0.5))
        if rng.random() < 0.3:  # a second plate lower on the same pole
            q.add(2, z - 0.1, sign, e + out * 0.5, rng.uniform(1.8, 2.3), z - 0.1)
        z += rng.uniform(8.0, 22.0)
    if rng.random() < 0.45:
        o, f = st.outer[side], st.facades[side]
        x = (o + f) / 2 if o != f else e + out * 1.3
        for z in np.arange(rng.uniform(3.0, 12.0), min(st.end, 80.0), rng.uniform(7.0, 14.0)):
            q.add(2, float(z), tree, x, float(z), rng.uniform(5.0, 11.0))


def _sidewalk(q: _Queue, st: Street, side: int) -> None:
    """Pedestrians (alone or in groups), parked two-wheelers, clutter and maybe a railing."""
    rng, e, o, out = q.rng, st.edges[side], st.outer[side], 1.0 if side else -1.0
    for _ in range(rng.poisson(1.8 if st.park[side] else 4.0)):
        # Most people walk near the curb: the house side has doors, bins and bicycles.
        near = 0.4 + rng.beta(1.0, 3.0) * (abs(o - e) - 0.8)
        x, z = e + out * near, _loguniform(rng, 12.0, 50.0)
        for _ in range(1 if rng.random() < 0.8 else int(rng.integers(2, 4))):
            tall = rng.uniform(1.55, 1.95) if rng.random() < 0.9 else rng.uniform(1.1, 1.4)
            q.add(0, z, pedestrian, x, z, tall)
            x, z = x + rng.normal(0.0, 0.5), z + rng.uniform(0.5, 1.5)
    for motor, chance in ((False, 0.5), (True, 0.3)):
        for _ in range(int(rng.integers(1, 4)) if rng.random() < chance else 0):
            z = rng.uniform(6.0, 40.0)
            q.add(0, z, two_wheeler, o - out * 0.6, z, motor, False)
    if rng.random() < 0.3:
        z = rng.uniform(6.0, 40.0)
        q.add(0, z, clutter, e + out * rng.uniform(0.3, abs(o - e)), z)
    if rng.random() < 0.12:
        z = rng.uniform(3.0, 10.0)
        q.add(1, z, barrier, e + out * 0.3, (z, z + rng.uniform(10.0, 40.0)), 1.0, FENCE)


def _road(q: _Queue, st: Street, rail: float | None) -> None:
    """Parked and moving vehicles, a tram on its rails, riders and crossing pedestrians."""
    rng, taken = q.rng, []

    def add(x: float, z: float, size: Span, fn: Callable[..., None], *args: object) -> None:
        box = (x - size[0], x + size[0], z, z + size[1])  # footprint: no two vehicles overlap
        if not any(
            b[0] < box[1] and box[0] < b[1] and b[2] < box[3] and box[2] < b[3] for b in taken
        ):
            taken.append(box)
            q.add(2, z, fn, x, z, *args)

    for side, inward in ((0, 1.0), (1, -1.0)):
        x = st.edges[side] + inward * 1.1
        if abs(x - st.lanes[-side]) > 2.4 and rng.random() < 0.7:  # a parking lane
            z = rng.uniform(2.0, 12.0)
            while z < 60.0:
                add(x, z, (0.95, 5.0), car, pick(rng, CAR_PAINT), side == 1)
                z += rng.uniform(5.0, 9.0) if rng.random() < 0.8 else rng.uniform(10.0, 25.0)
    if rail is not None and rng.random() < 0.75:
        add(rail, rng.uniform(10.0, 40.0), (1.35, 32.0), tram, pick(rng, TRAM_PAINT, 8))
    for fn, count, size, paint in (
        (truck, rng.random() < 0.2, (1.3, 11.0), CAR_PAINT),
        (bus, rng.random() < 0.18, (1.3, 14.0), BUS_PAINT),
        (car, rng.poisson(1.8), (0.95, 5.0), CAR_PAINT),
    ):
        for _ in range(int(count)):
            k = int(rng.integers(len(st.lanes)))
            x, z = st.lanes[k] + rng.normal(0.0, 0.2), _loguniform(rng, 7.0, 80.0)
            add(x, z, size, fn, pick(rng, paint), k >= st.oncoming)
    for _ in range(int(rng.integers(1, 4)) if rng.random() < 0.7 else 0):
        x, z = st.lanes[-1] + rng.uniform(0.5, 1.5), _loguniform(rng, 5.0, 35.0)
        add(x, z, (0.4, 2.0), two_wheeler, rng.random() < 0.4, True)
    for _ in range(int(rng.integers(1, 5)) if rng.random() < 0.55 else 0):
        x, z = rng.uniform(st.edges[0] + 0.5, st.edges[1] - 0.5), rng.uniform(10.0, 35.0)
        add(x, z, (0.3, 0.5), pedestrian, rng.uniform(1.55, 1.95))


def draw_street(
    cv: Canvas, rng: np.random.Generator, st: Street, shadow: ImageDraw.ImageDraw
) -> None:
    """Paint the whole scene far to near; cast the facades' shadows on ``shadow``."""
    draw_backdrop(cv, rng, st)
    draw_ground(cv, rng, st)
    q = _Queue(cv, rng)
    _road(q, st, draw_markings(cv, rng, st))
    draw_edges(cv, rng, st)
    for side in (0, 1):
        _poles_and_trees(q, st, side)
        _sidewalk(q, st, side)
    q.draw()
    if rng.random() < 0.5:  # low sun on one side
        x = st.facades[int(rng.integers(2))]
        shadow.polygon(cv.flat(x, x * (1.0 - rng.uniform(0.2, 0.8)), 1.0, st.end), fill=255)
    if rng.random() < 0.35:  # the ego vehicle's hood
        w, h = cv.label.im.size
        top = h * (1.0 - rng.uniform(0.03, 0.07))
        cv.ellipse([-0.2 * w, top, 1.2 * w, top + 0.5 * h], IGNORE_INDEX, (25, 25, 30), 1.0)
