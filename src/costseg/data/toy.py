"""Procedural street scenes: the project's embedded default dataset (nothing to download).

Each scene is a dash-cam view of a street in perspective: road with lane markings, sidewalks,
terrain, facades with windows, a little sky, poles with signs and lights, vehicles, persons and
riders at many depths. Labels are the 19 Cityscapes train ids (255 = ignore) with roughly
Cityscapes' class frequencies and layout. Images get texture noise, haze, shadows, per-scene
lighting and blur, so that small, far and occluded objects stay genuinely uncertain.

>>> image, label = StreetScenes(split="val", length=2, size=(64, 128))[0]
>>> image.shape, image.dtype, label.shape, label.dtype
(torch.Size([3, 64, 128]), torch.uint8, torch.Size([64, 128]), torch.int64)
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from functools import lru_cache, partial

import numpy as np
import torch
from PIL import Image, ImageDraw, ImageFilter
from torch.utils.data import Dataset

from costseg.classes import IGNORE_INDEX
from costseg.data import toy_draw as td

MIN_SIZE = 64
SPLITS = {"train": 0, "val": 1, "test": 2}
CAR_PAINT: tuple[td.RGB, ...] = (
    (190, 190, 195), (30, 30, 35), (225, 225, 225), (150, 25, 30), (30, 55, 120), (80, 80, 85),
    (40, 75, 55), (120, 110, 90),
)  # fmt: skip
BUS_PAINT: tuple[td.RGB, ...] = ((235, 190, 30), (200, 40, 40), (230, 120, 30), (40, 90, 170))
TRAM_PAINT: tuple[td.RGB, ...] = ((235, 235, 225), (215, 225, 200), (200, 215, 225))
# Texture amplitude per train id (1/16 of the noise bank's unit) of fine grain, leaf-sized blobs
# and large blotches: part of each class's characteristic look.
_AMP = np.zeros((3, 256), dtype=np.int16)
_AMP[:, IGNORE_INDEX] = (8, 4, 8)
for _cls, _amp in {
    td.ROAD: (7, 0, 5), td.SIDEWALK: (8, 2, 5), td.BUILDING: (5, 0, 8), td.WALL: (8, 3, 12),
    td.FENCE: (6, 0, 4), td.POLE: (3, 0, 2), td.LIGHT: (2, 0, 0), td.SIGN: (2, 0, 0),
    td.VEGETATION: (12, 22, 10), td.TERRAIN: (10, 12, 14), td.SKY: (1, 0, 7),
    td.PERSON: (4, 0, 3), td.RIDER: (4, 0, 3), td.CAR: (3, 0, 3), td.TRUCK: (4, 0, 4),
    td.BUS: (3, 0, 3), td.TRAIN: (3, 0, 3), td.MOTORCYCLE: (4, 0, 2), td.BICYCLE: (4, 0, 2),
}.items():  # fmt: skip
    _AMP[:, _cls] = _amp
Span = tuple[float, float]


@dataclass(frozen=True)
class Street:
    """One scene's layout: camera, X (m) of the road edges, sidewalks' outer edges and facades."""

    cam: td.Camera
    edges: tuple[float, float]
    outer: tuple[float, float]
    facades: tuple[float, float]
    park: tuple[bool, bool]
    lanes: tuple[float, ...]  # lane centres; lanes before ``oncoming`` come towards the camera
    oncoming: int
    end: float  # depth where the street ends in a cross row of buildings
    sky: tuple[td.RGB, td.RGB]  # zenith and horizon (= haze) colours
    haze_range: float

    @classmethod
    def sample(cls, rng: np.random.Generator, h: int, w: int) -> Street:
        f, cx, hy, hc = rng.uniform(
            (0.9 * w, 0.46 * w, 0.38 * h, 1.3), (1.1 * w, 0.54 * w, 0.46 * h, 1.7)
        )
        n, lw = int(rng.integers(2, 5)), rng.uniform(2.9, 3.5)
        oncoming = n // 2 if rng.random() < 0.7 else 0  # else a one-way street
        ego = int(rng.integers(oncoming, n))  # the camera drives in a lane of its direction
        lanes = tuple((k - ego) * lw for k in range(n))
        parking = np.where(rng.random(2) < 0.6, rng.uniform(2.0, 2.5, 2), 0.0)
        edges = (lanes[0] - lw / 2 - parking[0], lanes[-1] + lw / 2 + parking[1])
        walk, park = rng.uniform(3.5, 6.5, 2), rng.random(2) < 0.25
        verge = np.where(rng.random(2) < 0.6, rng.uniform(1.5, 5.0, 2), 0.0)
        verge += park * rng.uniform(3.0, 12.0, 2)
        outer = (edges[0] - walk[0], edges[1] + walk[1])
        facades = (outer[0] - verge[0], outer[1] + verge[1])
        clear = rng.random() < 0.6
        sky = ((70, 130, 200), (190, 210, 230)) if clear else ((165, 170, 180), (215, 215, 220))
        return cls(
            td.Camera(f, cx, hy, hc),
            edges,
            outer,
            facades,
            (bool(park[0]), bool(park[1])),
            lanes,
            oncoming,
            rng.uniform(60.0, 180.0),
            (td.jitter(rng, sky[0], 10), td.jitter(rng, sky[1], 8)),
            rng.uniform(120.0, 500.0),
        )

    def sky_gradient(self, h: int, w: int) -> Image.Image:
        """(W, H) RGB sky, deeper at the top, paler at the horizon."""
        t = np.clip(np.arange(h) / self.cam.hy, 0.0, 1.0)[:, None]
        rows = ((1.0 - t) * np.asarray(self.sky[0]) + t * np.asarray(self.sky[1])).astype(np.uint8)
        return Image.fromarray(rows[:, None, :]).resize((w, h), Image.NEAREST)


def _backdrop(cv: td.Canvas, rng: np.random.Generator, st: Street) -> None:
    """The cross row at the street's end, then the facades (or park tree lines) of both sides."""
    x = st.facades[0]
    while x < st.facades[1]:
        x1, height = min(st.facades[1], x + rng.uniform(5.0, 25.0)), rng.uniform(8.0, 28.0)
        cls, colour = (
            (td.BUILDING, td.pick(rng, td.FACADES))
            if rng.random() < 0.7
            else (td.VEGETATION, td.jitter(rng, td.GREEN))
        )
        cv.poly(cv.front(x, x1, st.end, 0.0, height), cls, colour, st.end)
        x = x1
    for x, park in zip(st.facades, st.park, strict=True):
        z = 1.0
        while z < st.end:
            zs = (z, st.end if park else min(st.end, z + rng.uniform(8.0, 30.0)))
            if park or rng.random() < 0.12:
                td.green_wall(cv, rng, x, zs, rng.uniform(7.0, 15.0))
            else:
                td.building(cv, rng, x, zs, rng.uniform(10.0, 30.0))
            z = zs[1]


def _ground(cv: td.Canvas, rng: np.random.Generator, st: Street) -> None:
    """Terrain, paved sidewalks with curbs and the road."""
    p, z0, z1 = cv.cam.p, 1.0, st.end
    for e, o, f in zip(st.edges, st.outer, st.facades, strict=True):
        if o != f:
            cv.poly(cv.flat(o, f, z0, z1), td.TERRAIN, td.jitter(rng, (125, 140, 65)), z0)
        walk = td.jitter(rng, (150, 140, 130), 14)
        cv.poly(cv.flat(e, o, z0, z1), td.SIDEWALK, walk, z0)
        for z in np.arange(rng.uniform(1.0, 3.0), 40.0, rng.uniform(1.2, 2.5)).tolist():
            cv.line([p(e, 0.0, z), p(o, 0.0, z)], None, td.shade(walk, 0.8), z, 1)
        if abs(o - e) > 4.0 and rng.random() < 0.35:  # a grass strip along the curb
            grass = (e + 0.3 * np.sign(o - e), e + rng.uniform(1.2, 2.2) * np.sign(o - e))
            cv.poly(cv.flat(*grass, z0, z1), td.TERRAIN, td.jitter(rng, (125, 140, 65)), z0)
        cv.poly(cv.side(e, z0, z1, 0.0, 0.15), td.SIDEWALK, td.shade(walk, 1.15), z0)
    cv.poly(cv.flat(*st.edges, z0, z1), td.ROAD, td.jitter(rng, (90, 90, 92), 12), z0)


def _markings(cv: td.Canvas, rng: np.random.Generator, st: Street) -> float | None:
    """Lane lines, maybe a zebra crossing and tram rails; returns the rails' X, if any."""
    paint, lw = td.jitter(rng, (215, 215, 210), 12), st.lanes[1] - st.lanes[0]
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


def _edges(cv: td.Canvas, rng: np.random.Generator, st: Street) -> None:
    """Walls, fences and hedges along the outer edges of the sidewalks."""
    for o, f in zip(st.outer, st.facades, strict=True):
        x = o if o != f else 0.99 * f
        for cls, chance in ((td.WALL, 0.45), (td.FENCE, 0.4), (td.VEGETATION, 0.3)):
            if rng.random() < chance:
                z0 = rng.uniform(2.0, 30.0)
                zs = (z0, min(st.end, z0 + rng.uniform(5.0, 40.0)))
                if cls == td.VEGETATION:
                    td.green_wall(cv, rng, x, zs, rng.uniform(0.8, 2.0))
                else:
                    td.barrier(cv, rng, x, zs, rng.uniform(1.0, 2.6), cls)


def _loguniform(rng: np.random.Generator, lo: float, hi: float) -> float:
    # Depths: as many objects between 5 and 10 m as between 30 and 60 m.
    return float(np.exp(rng.uniform(np.log(lo), np.log(hi))))


def _pedestrian(cv: td.Canvas, rng: np.random.Generator, x: float, z: float, tall: float) -> None:
    td.figure(cv, rng, cv.cam.p(x, 0.0, z), tall * cv.cam.f / z, td.PERSON, z)


class _Queue:
    """Drawings made far to near: sorted by (layer, -depth, order of queueing).

    Layer 0 stands on a sidewalk, 1 is a railing at the curb, 2 stands at the curb or on the road
    (so it covers the sidewalk behind it).
    """

    def __init__(self, cv: td.Canvas, rng: np.random.Generator) -> None:
        self.cv, self.rng = cv, rng
        self.items: list[tuple[int, float, int, Callable[[], None]]] = []

    def add(self, layer: int, z: float, fn: Callable[..., None], *args: object) -> None:
        self.items.append((layer, -z, len(self.items), partial(fn, self.cv, self.rng, *args)))

    def draw(self) -> None:
        for *_, draw in sorted(self.items, key=lambda item: item[:3]):
            draw()


def _poles_and_trees(q: _Queue, st: Street, side: int) -> None:
    """Poles with signs, lights or lamps along one curb, and maybe a row of trees."""
    rng, e, out = q.rng, st.edges[side], 1.0 if side else -1.0  # out: away from the road
    z = rng.uniform(3.0, 15.0)
    while z < min(st.end - 5.0, 80.0):
        kind = str(rng.choice(["sign", "light", "lamp"], p=[0.4, 0.35, 0.25]))
        arm = {"sign": 0.0, "light": rng.uniform(2.0, 5.0), "lamp": 1.5}[kind]
        q.add(2, z, td.pole, e + out * 0.5, z, kind, -out * arm * (rng.random() < 0.5))
        if rng.random() < 0.3:  # a second plate lower on the same pole
            q.add(2, z - 0.1, td.sign, e + out * 0.5, rng.uniform(1.8, 2.3), z - 0.1)
        z += rng.uniform(8.0, 22.0)
    if rng.random() < 0.45:
        o, f = st.outer[side], st.facades[side]
        x = (o + f) / 2 if o != f else e + out * 1.3
        for z in np.arange(rng.uniform(3.0, 12.0), min(st.end, 80.0), rng.uniform(7.0, 14.0)):
            q.add(2, float(z), td.tree, x, float(z), rng.uniform(5.0, 11.0))


def _sidewalk(q: _Queue, st: Street, side: int) -> None:
    """Pedestrians (alone or in groups), parked two-wheelers, clutter and maybe a railing."""
    rng, e, o, out = q.rng, st.edges[side], st.outer[side], 1.0 if side else -1.0
    for _ in range(rng.poisson(1.8 if st.park[side] else 3.5)):
        x, z = e + out * rng.uniform(0.5, abs(o - e) - 0.4), _loguniform(rng, 3.5, 30.0)
        for _ in range(1 if rng.random() < 0.8 else int(rng.integers(2, 4))):
            tall = rng.uniform(1.55, 1.95) if rng.random() < 0.9 else rng.uniform(1.1, 1.4)
            q.add(0, z, _pedestrian, x, z, tall)
            x, z = x + rng.normal(0.0, 0.5), z + rng.uniform(0.5, 1.5)
    for motor, chance in ((False, 0.5), (True, 0.3)):
        for _ in range(int(rng.integers(1, 4)) if rng.random() < chance else 0):
            z = rng.uniform(6.0, 40.0)
            q.add(0, z, td.two_wheeler, o - out * 0.6, z, motor, False)
    if rng.random() < 0.3:
        z = rng.uniform(6.0, 40.0)
        q.add(0, z, td.clutter, e + out * rng.uniform(0.3, abs(o - e)), z)
    if rng.random() < 0.12:
        z = rng.uniform(3.0, 10.0)
        q.add(1, z, td.barrier, e + out * 0.3, (z, z + rng.uniform(10.0, 40.0)), 1.0, td.FENCE)


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
                add(x, z, (0.95, 5.0), td.car, td.pick(rng, CAR_PAINT), side == 1)
                z += rng.uniform(5.0, 9.0) if rng.random() < 0.8 else rng.uniform(10.0, 25.0)
    if rail is not None and rng.random() < 0.75:
        add(rail, rng.uniform(10.0, 40.0), (1.35, 32.0), td.tram, td.pick(rng, TRAM_PAINT, 8))
    for fn, count, size, paint in (
        (td.truck, rng.random() < 0.2, (1.3, 11.0), CAR_PAINT),
        (td.bus, rng.random() < 0.18, (1.3, 14.0), BUS_PAINT),
        (td.car, rng.poisson(1.8), (0.95, 5.0), CAR_PAINT),
    ):
        for _ in range(int(count)):
            k = int(rng.integers(len(st.lanes)))
            x, z = st.lanes[k] + rng.normal(0.0, 0.2), _loguniform(rng, 7.0, 80.0)
            add(x, z, size, fn, td.pick(rng, paint), k >= st.oncoming)
    for _ in range(int(rng.integers(1, 4)) if rng.random() < 0.7 else 0):
        x, z = st.lanes[-1] + rng.uniform(0.5, 1.5), _loguniform(rng, 5.0, 35.0)
        add(x, z, (0.4, 2.0), td.two_wheeler, rng.random() < 0.4, True)
    for _ in range(int(rng.integers(1, 5)) if rng.random() < 0.55 else 0):
        x, z = rng.uniform(st.edges[0] + 0.5, st.edges[1] - 0.5), rng.uniform(6.0, 25.0)
        add(x, z, (0.3, 0.5), _pedestrian, rng.uniform(1.55, 1.95))


def _draw_street(
    cv: td.Canvas, rng: np.random.Generator, st: Street, shadow: ImageDraw.ImageDraw
) -> None:
    """Paint the whole scene far to near; cast the facades' shadows on ``shadow``."""
    _backdrop(cv, rng, st)
    _ground(cv, rng, st)
    q = _Queue(cv, rng)
    _road(q, st, _markings(cv, rng, st))
    _edges(cv, rng, st)
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


@lru_cache(maxsize=4)
def _noise_bank(h: int, w: int) -> tuple[np.ndarray, ...]:
    """Fixed (2h, 2w) int16 noise fields (grain, leaves, blotches) that scenes crop at random.

    Fresh Gaussian noise per image would dominate the generation time; a fixed bank cropped at
    per-scene offsets is as varied for a network and keeps every scene deterministic.
    """
    rng = np.random.default_rng(20190616)
    fields = [rng.normal(0.0, 16.0, (2 * h, 2 * w))]
    for cell in (max(2, h // 90), max(4, h // 16)):
        small = rng.normal(0.0, 1.0, (2 * h // cell + 1, 2 * w // cell + 1)).astype(np.float32)
        big = np.asarray(Image.fromarray(small, mode="F").resize((2 * w, 2 * h), Image.BILINEAR))
        fields.append(big * (16.0 / big.std()))
    return tuple(np.clip(f, -127, 127).astype(np.int16) for f in fields)


def _texture(rgb: np.ndarray, label: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Add class-dependent texture noise to the (H, W, 3) uint8 image."""
    h, w = label.shape
    noise = np.zeros((h, w), dtype=np.int16)
    for amp, field in zip(
        (_AMP * rng.uniform(0.6, 1.4)).astype(np.int16), _noise_bank(h, w), strict=True
    ):
        y, x = rng.integers(0, h + 1), rng.integers(0, w + 1)
        noise += amp[label] * field[y : y + h, x : x + w]
    noise >>= 4
    return np.clip(rgb.astype(np.int16) + noise[..., None], 0, 255).astype(np.uint8)


def _photograph(
    image: Image.Image, label: np.ndarray, shadow: Image.Image, rng: np.random.Generator
) -> np.ndarray:
    """Soft shadows, texture, per-scene exposure, colour cast and gamma, then lens blur."""
    h = label.shape[0]
    if shadow.getbbox():
        dark = image.point((np.arange(256) * rng.uniform(0.45, 0.7)).astype(int).tolist() * 3)
        image = Image.composite(dark, image, shadow.filter(ImageFilter.BoxBlur(h / 200)))
    image = Image.fromarray(_texture(np.asarray(image), label, rng))
    gain = rng.uniform(0.7, 1.25) * (1.0 + rng.normal(0.0, 0.05, 3))
    ramp = (np.arange(256) / 255.0) ** rng.uniform(0.8, 1.25)
    image = image.point(
        np.clip(255.0 * ramp * gain[:, None], 0, 255).astype(np.uint8).ravel().tolist()
    )
    sharp = rng.random() < 0.85
    radius = h / 256 * (rng.uniform(0.4, 0.8) if sharp else rng.uniform(1.2, 1.8))
    return np.array(image.filter(ImageFilter.BoxBlur(radius)))


def _check_size(size: tuple[int, int]) -> tuple[int, int]:
    ok = len(size) == 2 and all(isinstance(s, (int, np.integer)) for s in size)
    if not ok or min(size) < MIN_SIZE:
        raise ValueError(f"size must be (height, width) integers >= {MIN_SIZE}; got {size!r}")
    return int(size[0]), int(size[1])


def render_scene(
    rng: np.random.Generator, size: tuple[int, int] = (256, 512)
) -> tuple[np.ndarray, np.ndarray]:
    """Render one street scene, a pure function of the generator's state.

    Args:
        rng: the source of all randomness.
        size: (H, W) in pixels, each >= 64; the geometry scales with it.

    Returns:
        image (H, W, 3) uint8 RGB and label (H, W) uint8 train ids 0..18, 255 = ignore.

    >>> image, label = render_scene(np.random.default_rng(0), size=(64, 128))
    >>> image.shape, label.shape, label.dtype.name
    ((64, 128, 3), (64, 128), 'uint8')
    """
    h, w = _check_size(size)
    st = Street.sample(rng, h, w)
    image, label = st.sky_gradient(h, w), Image.new("L", (w, h), td.SKY)
    shadow = Image.new("L", (w, h), 0)
    canvas = td.Canvas(image, label, st.cam, st.sky[1], st.haze_range)
    _draw_street(canvas, rng, st, ImageDraw.Draw(shadow))
    labels = np.array(label)
    return _photograph(image, labels, shadow, rng), labels


class StreetScenes(Dataset):
    """Procedural street scenes as a map-style dataset, deterministic per (seed, split, index).

    Args:
        split: "train", "val" or "test"; each draws from its own random stream.
        length: number of scenes.
        size: (H, W) of every image, each >= 64.
        seed: non-negative integer choosing the whole family of scenes.

    Items are ``(image, label)``: (3, H, W) uint8 RGB and (H, W) int64 train ids (255 = ignore).

    >>> a, b = StreetScenes("val", 3, (64, 128))[2], StreetScenes("val", 3, (64, 128))[-1]
    >>> bool((a[0] == b[0]).all() and (a[1] == b[1]).all())
    True
    """

    def __init__(
        self,
        split: str = "train",
        length: int = 1000,
        size: tuple[int, int] = (256, 512),
        seed: int = 0,
    ) -> None:
        if split not in SPLITS:
            raise ValueError(f"split must be one of {sorted(SPLITS)}; got {split!r}")
        for name, value in (("length", length), ("seed", seed)):
            if not isinstance(value, (int, np.integer)) or value < 0:
                raise ValueError(f"{name} must be a non-negative integer; got {value!r}")
        self.split, self.length, self.size, self.seed = (
            split,
            int(length),
            _check_size(size),
            int(seed),
        )

    def __len__(self) -> int:
        return self.length

    def __getitem__(self, index: int) -> tuple[torch.Tensor, torch.Tensor]:
        if not -self.length <= index < self.length:
            raise IndexError(f"index {index} is out of range for {self.length} scenes")
        rng = np.random.default_rng([self.seed, SPLITS[self.split], int(index) % self.length])
        image, label = render_scene(rng, self.size)
        return torch.from_numpy(image).permute(2, 0, 1).contiguous(), torch.from_numpy(
            label.astype(np.int64)
        )
