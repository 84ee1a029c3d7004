"""``street3d``: a 3D street seen by a handheld camera, drawn by the quad ray caster (``synth.raycast``).

Not Gaussians, and not a picture: geometry in metres, a moving camera with parallax. World frame: x
along the street (east), y across it (north), z up; the ground is z = 0.

- the street: a 9 m road (two lanes, x-travelling cars at y = -1.7 eastwards and y = +1.7 westwards, a
  parking strip on the north side), 3 m pavements on 12 cm curbs, building fronts on both sides
  (6-10 m wide, 10-20 m tall, set back 0-0.6 m: their side walls show) from x = -15 to 100 m, and a
  building across the street's end; lamp posts, bollards along the south curb, bins, a cabinet, an
  advertising pillar and planters (turned boxes), parked cars; procedural textures
  (``synth.street3d_textures``) lit by one sun (a shade per face), a sky gradient;
- traffic: cars (a body and a cabin box) in both lanes at a speed per lane (7-10 m/s), a deterministic
  function of (seed, lane, slot) as in ``synth.traffic``: the scene is defined at every t;
- the camera: a DAVIS346 held by someone walking east along the south pavement (0.9 m/s, drifting
  across by +-0.3 m), looking along the street and towards its north side (yaw 18 +- 13 degrees,
  pitch -4 +- 2, roll +- 1), with the hand's bob and shake (a few mm, a few tenths of a degree, at
  2.7 to 6.3 Hz): sums of sines, smooth at every order, their phases drawn from the seed;
- a second camera on the same rig (``RIG``: 0.3 m to the first one's left, turned 5 degrees right, the
  same intrinsics): the novel views.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from edmcgs.errors import InvalidInputError
from edmcgs.geometry import Intrinsics
from edmcgs.synth import street3d_textures as tx
from edmcgs.synth.orbit import DAVIS346
from edmcgs.synth.raycast import NEAR, QUAD_FIELDS, Frame, Sky, Textures, box, quad, render

FULL_WIDTH, FULL_HEIGHT = DAVIS346.width, DAVIS346.height
ROAD_HALF = 4.5
"""Metres from the street's axis to each curb."""
FACADE_Y = 7.5
"""Metres from the street's axis to the building line."""
CURB = 0.12
STREET = (-15.0, 100.0)
"""x range of the buildings; the building across the street stands beyond it."""
LANES = ((-1.7, 1), (1.7, -1))
"""(y, direction along x) of the two traffic lanes."""
TRAFFIC_SPAN = (-25.0, 105.0)
"""Cars are drawn while their centre is within this x range (beyond it they are out of any view)."""
SUN = np.array([-0.35, -0.55, 0.75]) / np.linalg.norm([-0.35, -0.55, 0.75])
"""Unit vector towards the sun (south-west, high): the north side's fronts are lit, the south's shaded."""
AMBIENT = 0.55
SKY = Sky(horizon=0.78, zenith=0.6)
RIG = np.array([[math.cos(math.radians(5)), 0.0, math.sin(math.radians(5)), -0.3],
                [0.0, 1.0, 0.0, 0.0],
                [-math.sin(math.radians(5)), 0.0, math.cos(math.radians(5)), 0.0],
                [0.0, 0.0, 0.0, 1.0]])
"""The novel camera in the event camera's frame (OpenCV axes): 0.3 m to its left (-x), turned 5 degrees
to its right (about its y axis), so that their views overlap. Its pose is c2w(t) @ RIG."""

# the hand: channel -> (value at t = 0 before the sines, rate per second, ((amplitude, hz), ...))
_DEG = math.pi / 180
WALK = {
    "x": (0.0, 0.9, ((0.04, 0.9),)),  # walking east, the surge of the steps
    "y": (-6.0, 0.0, ((0.3, 0.11), (0.02, 0.9))),  # drifting across the pavement, the sway of the steps
    "z": (1.5, 0.0, ((0.012, 1.8),)),  # the bob of the steps
    "yaw": (18 * _DEG, 0.0, ((10 * _DEG, 0.09), (3 * _DEG, 0.23))),  # looking around
    "pitch": (-4 * _DEG, 0.0, ((2 * _DEG, 0.15),)),
    "roll": (0.0, 0.0, ((1 * _DEG, 0.2),)),
}
SHAKE_M = ((0.0015, 3.1), (0.0012, 4.7), (0.0008, 6.3))
"""The hand's shake on each of x, y, z: (amplitude m, Hz)."""
SHAKE_RAD = ((0.15 * _DEG, 2.7), (0.1 * _DEG, 4.1), (0.06 * _DEG, 5.9))
"""The hand's shake on each of yaw, pitch, roll: (amplitude rad, Hz)."""
_R0 = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
"""Camera axes at yaw = pitch = roll = 0: looking east (+x), x right (-y), y down (-z)."""


def _check_t(t_s) -> float:
    t_s = float(t_s)
    if not math.isfinite(t_s):
        raise InvalidInputError(f"t_s must be a finite time in seconds, got {t_s!r}")
    return t_s


class HandheldPath:
    """The walking, looking-around, shaking camera of the module docstring; ``c2w`` at any times."""

    def __init__(self, seed: int, moving: bool = True) -> None:
        rng = np.random.default_rng(np.random.SeedSequence([int(seed), 5]))
        self.moving = bool(moving)
        self._terms = {}
        for name, (offset, rate, waves) in WALK.items():
            shake = SHAKE_M if name in ("x", "y", "z") else SHAKE_RAD
            waves = waves + shake
            amp, hz = np.array([a for a, _ in waves]), np.array([f for _, f in waves])
            self._terms[name] = (offset, rate, amp, 2 * np.pi * hz, rng.uniform(0, 2 * np.pi, len(waves)))

    def _value(self, name: str, t: np.ndarray) -> np.ndarray:
        offset, rate, amp, omega, phase = self._terms[name]
        return offset + rate * t + (amp * np.sin(np.multiply.outer(t, omega) + phase)).sum(axis=-1)

    def c2w(self, t_s) -> np.ndarray:
        """Camera-to-world float64 [K, 4, 4] (OpenCV axes) at times t_s [K] (seconds)."""
        t = np.atleast_1d(np.asarray(t_s, np.float64))
        if not np.isfinite(t).all():
            raise InvalidInputError("t_s must be finite times in seconds")
        if not self.moving:
            t = np.zeros_like(t)
        yaw, pitch, roll = (self._value(n, t) for n in ("yaw", "pitch", "roll"))
        cy, sy, cp, sp = np.cos(yaw), np.sin(yaw), np.cos(pitch), np.sin(pitch)
        cr, sr = np.cos(roll), np.sin(roll)
        one, zero = np.ones_like(t), np.zeros_like(t)
        rz = np.stack([cy, -sy, zero, sy, cy, zero, zero, zero, one], -1).reshape(-1, 3, 3)
        rx = np.stack([one, zero, zero, zero, cp, -sp, zero, sp, cp], -1).reshape(-1, 3, 3)  # about camera x
        rr = np.stack([cr, -sr, zero, sr, cr, zero, zero, zero, one], -1).reshape(-1, 3, 3)  # about camera z
        out = np.zeros((len(t), 4, 4))
        out[:, :3, :3] = rz @ _R0 @ rx @ rr
        out[:, :3, 3] = np.stack([self._value(n, t) for n in ("x", "y", "z")], -1)
        out[:, 3, 3] = 1.0
        return out


@dataclass(frozen=True)
class Car:
    """A car in a lane: its centre's x is ``direction * speed * (t - t_pass)``."""

    lane: int
    slot: int
    model: int
    """Index into ``street3d_textures.CAR_MODELS``."""
    tone: float
    """Its paint's luminance factor."""
    t_pass: float
    """When it passes x = 0."""
    speed: float
    direction: int
    y: float

    def x_at(self, t_s: float) -> float:
        return self.direction * self.speed * (t_s - self.t_pass)


@dataclass(frozen=True)
class _Street:
    """The static street: its quads and the textures of everything (cars' too)."""

    quads: np.ndarray
    textures: Textures
    ids: dict


def _car_quads(model: int, tone: float, direction: int, ids: dict, x: float, y: float) -> np.ndarray:
    """A car's quads, its centre at (x, y) on the road, facing +x (direction 1) or -x (-1)."""
    m = tx.CAR_MODELS[model]
    t = {name: ids[f"car{model}_{name}"] for name in ("side", "front", "rear", "top", "cabin_side", "glass")}
    front, rear = ("+x", "-x") if direction > 0 else ("-x", "+x")
    body = box((x, y, 0.0), (m.length, m.width, m.body),
               {front: (t["front"], tone), rear: (t["rear"], tone), "+y": (t["side"], tone),
                "-y": (t["side"], tone), "top": (t["top"], tone)}, light=SUN, ambient=AMBIENT)
    cabin = box((x - direction * m.cabin_shift, y, m.body), (m.cabin_length, m.width - 0.12, m.cabin),
                {front: (t["glass"], tone), rear: (t["glass"], tone), "+y": (t["cabin_side"], tone),
                 "-y": (t["cabin_side"], tone), "top": (t["top"], tone)}, light=SUN, ambient=AMBIENT)
    return np.concatenate([body, cabin])


@lru_cache(maxsize=4)
def _street(seed: int, res: int) -> _Street:
    """Lay out the street and draw its textures (deterministic in (seed, res); shared)."""
    rng = np.random.default_rng(np.random.SeedSequence([seed, 13]))
    key = 1000 * seed
    images: list[tuple[np.ndarray, float]] = []
    ids: dict[str, int] = {}

    def add(name, made):
        ids[name] = len(images)
        images.append(made)

    for name, make in (("road", tx.road), ("pavement", tx.pavement), ("curb", tx.curb), ("wall", tx.wall),
                       ("metal", tx.metal), ("bollard", tx.bollard), ("bin", tx.bin_texture),
                       ("cabinet", tx.cabinet), ("poster", tx.poster), ("concrete", tx.concrete),
                       ("soil", tx.soil)):
        add(name, make(key + 10 * len(images), res))
    for i, m in enumerate(tx.CAR_MODELS):
        for name, made in tx.car_textures(m, key + 500 + 10 * i, res).items():
            add(f"car{i}_{name}", made)

    rows = []
    length, x0 = STREET[1] + 10.0 - STREET[0], STREET[0]
    rows.append(quad((x0, ROAD_HALF, 0.0), (length, 0, 0), (0, -2 * ROAD_HALF, 0), ids["road"],
                     _lit((0, 0, 1))))
    width = FACADE_Y + 1.0 - ROAD_HALF  # on under the buildings (set back by up to 0.6 m)
    for side in (1, -1):  # pavements: a top and a curb towards the road
        rows.append(box((x0 + 0.5 * length, side * (ROAD_HALF + 0.5 * width), 0.0), (length, width, CURB),
                        {"top": (ids["pavement"], 1.0), ("-y" if side > 0 else "+y"): (ids["curb"], 1.0)},
                        light=SUN, ambient=AMBIENT))
    # building fronts, their side walls where they stand out
    for side in (1, -1):
        x = STREET[0]
        while x < STREET[1] - 1.0:
            w = min(float(rng.uniform(6.0, 10.0)), STREET[1] - x)
            f = tx.Facade.draw(rng, w, key + 100 + len(ids))
            add(f"facade{len(ids)}", tx.facade(f, res))
            setback = float(rng.choice([0.0, 0.0, 0.3, 0.6]))
            front = "-y" if side > 0 else "+y"
            wall_uv = (float(rng.uniform(0, 10)), 0.0)
            rows.append(box((x + 0.5 * w, side * (FACADE_Y + setback + 6.0), CURB), (w, 12.0, f.height),
                            {front: (len(images) - 1, 1.0), "+x": (ids["wall"], 1.0, wall_uv),
                             "-x": (ids["wall"], 1.0, wall_uv)}, light=SUN, ambient=AMBIENT))
            x += w
    end = tx.Facade.draw(rng, 10.24, key + 99)
    add("facade_end", tx.facade(end, res))
    rows.append(box((STREET[1] + 5.0, 0.0, 0.0), (10.0, 60.0, end.height), {"-x": (ids["facade_end"], 1.0)},
                    light=SUN, ambient=AMBIENT))
    # street furniture
    post = {f: (ids["metal"], 1.0) for f in ("+x", "-x", "+y", "-y", "top")}
    for i in range(8):
        for side in (1, -1):
            rows.append(box((-10.0 + 16.0 * i + 5.0 * (side < 0), side * (ROAD_HALF + 0.35), CURB),
                            (0.16, 0.16, 6.0), post, light=SUN, ambient=AMBIENT))
    bollard = {f: (ids["bollard"], 1.0) for f in ("+x", "-x", "+y", "-y")} | {"top": (ids["metal"], 0.6)}
    for i in range(17):
        rows.append(box((-3.0 + 2.5 * i, -(ROAD_HALF + 0.3), CURB), (0.14, 0.14, 0.9), bollard,
                        light=SUN, ambient=AMBIENT))
    litter = {f: (ids["bin"], 1.0) for f in ("+x", "-x", "+y", "-y")} | {"top": (ids["metal"], 0.8)}
    for x, y in ((6.5, -7.0), (23.5, -7.0), (15.0, 7.0), (41.0, 7.0)):
        rows.append(box((x, y, CURB), (0.55, 0.55, 0.95), litter, light=SUN, ambient=AMBIENT))
    rows.append(box((12.0, -7.2, CURB), (0.8, 0.4, 1.3), {f: (ids["cabinet"], 1.0, (0.3 * k, 0.0)) for k, f in
                                                        enumerate(("+x", "-x", "+y", "-y", "top"))},
                    light=SUN, ambient=AMBIENT))
    rows.append(box((19.0, 5.9, CURB), (1.2, 1.2, 2.8), {f: (ids["poster"], 1.0, (0.2 * k, -0.1)) for k, f in
                                                       enumerate(("+x", "-x", "+y", "-y"))}
                    | {"top": (ids["metal"], 1.0)}, yaw=0.3, light=SUN, ambient=AMBIENT))
    for x, yaw in ((28.0, 0.2), (34.0, -0.15)):
        planter = {f: (ids["concrete"], 1.0) for f in ("+x", "-x", "+y", "-y")} | {"top": (ids["soil"], 1.0)}
        rows.append(box((x, 6.6, CURB), (1.4, 0.8, 0.7), planter, yaw=yaw, light=SUN, ambient=AMBIENT))
    x = 6.0
    while x < 75.0:  # parked cars in the north strip, facing west
        model = int(rng.integers(len(tx.CAR_MODELS)))
        rows.append(_car_quads(model, _tone(rng), -1, ids, x, 3.45 + float(rng.uniform(-0.05, 0.05))))
        x += tx.CAR_MODELS[model].length + float(rng.choice([0.8, 1.2, 6.0, 11.0]))
    quads = np.concatenate([np.reshape(r, (-1, QUAD_FIELDS)) for r in rows])
    return _Street(quads, Textures.build(images), ids)


def _lit(normal) -> float:
    return AMBIENT + (1 - AMBIENT) * max(0.0, float(np.asarray(normal, float) @ SUN))


def _tone(rng: np.random.Generator) -> float:
    """A car's paint: dark, mid or light."""
    pick = rng.random()
    return float(rng.uniform(0.12, 0.2) if pick < 0.3 else rng.uniform(0.35, 0.55) if pick < 0.6
                 else rng.uniform(0.7, 0.95))


class StreetScene:
    """The street at ``width`` x ``height`` (DAVIS346 intrinsics scaled), seeded.

    occupancy: probability that a lane's slot holds a car; moving_camera: False holds the camera at its
    pose at t = 0 (the scene's own motion only).
    """

    name = "street3d"

    def __init__(self, width: int = FULL_WIDTH, height: int = FULL_HEIGHT, *, seed: int = 0,
                 occupancy: float = 0.8, moving_camera: bool = True) -> None:
        self.check(width, height, seed, occupancy)
        self.width, self.height, self.seed = int(width), int(height), int(seed)
        self.occupancy = float(occupancy)
        self.intrinsics: Intrinsics = DAVIS346.scaled(self.width, self.height)
        res = 1 if self.width > FULL_WIDTH // 2 + 1 else 2  # texels: half the resolution, twice the size
        self._street = _street(self.seed, res)
        self.path = HandheldPath(self.seed, moving_camera)
        rng = np.random.default_rng(np.random.SeedSequence([self.seed, 7]))
        self.lanes = tuple((y, d, float(rng.uniform(7.0, 10.0)), float(rng.uniform(2.4, 3.6)))
                           for y, d in LANES)
        """(y, direction, speed m/s, slot period s) of each lane."""
        self._cars: dict[tuple[int, int], tuple[Car, np.ndarray] | None] = {}

    @staticmethod
    def check(width, height, seed, occupancy) -> None:
        """InvalidInputError unless these make a street."""
        for name, value in (("width", width), ("height", height)):
            if isinstance(value, bool) or not isinstance(value, int | np.integer) or not 8 <= value <= 4096:
                raise InvalidInputError(f"{name} must be an integer in 8..4096, got {value!r}")
        if isinstance(seed, bool) or not isinstance(seed, int | np.integer) or not 0 <= seed < 2**31:
            raise InvalidInputError(f"seed must be an integer in 0..2**31-1, got {seed!r}")
        if isinstance(occupancy, bool) or not (isinstance(occupancy, int | float) and 0 <= occupancy <= 1):
            raise InvalidInputError(f"occupancy must be in [0, 1], got {occupancy!r}")

    # ---------------------------------------------------------------- cameras
    def camera_at(self, t_s: float) -> np.ndarray:
        """The event camera's camera-to-world float64 [4, 4] at t_s (OpenCV axes)."""
        return self.path.c2w(_check_t(t_s))[0]

    def novel_camera_at(self, t_s: float) -> np.ndarray:
        """The novel camera's camera-to-world at t_s: ``camera_at(t_s) @ RIG``."""
        return self.camera_at(t_s) @ RIG

    # ---------------------------------------------------------------- traffic
    def _car(self, lane: int, slot: int) -> tuple[Car, np.ndarray] | None:
        key = (lane, slot)
        if key not in self._cars:
            y, direction, speed, period = self.lanes[lane]
            rng = np.random.default_rng(np.random.SeedSequence([self.seed, 11, lane, slot + 2**40]))
            draw = rng.random(3)
            made = None
            if draw[0] < self.occupancy:
                car = Car(lane, slot, int(draw[2] * len(tx.CAR_MODELS)), _tone(rng),
                          (slot + 0.6 * draw[1]) * period, speed, direction, y)
                made = (car, _car_quads(car.model, car.tone, direction, self._street.ids, 0.0, y))
            self._cars[key] = made
        return self._cars[key]

    def cars_at(self, t_s: float) -> list[Car]:
        """The cars on the street (within ``TRAFFIC_SPAN``) at t_s."""
        return [car for car, _ in self._cars_at(_check_t(t_s))]

    def _cars_at(self, t_s: float) -> list[tuple[Car, np.ndarray]]:
        found = []
        for lane, (_, direction, speed, period) in enumerate(self.lanes):
            # x = d v (t - t_pass) in the span  <=>  t_pass in [t - hi / (d v), t - lo / (d v)]
            ends = sorted(t_s - x / (direction * speed) for x in TRAFFIC_SPAN)
            for slot in range(math.floor(ends[0] / period) - 1, math.ceil(ends[1] / period) + 1):
                made = self._car(lane, slot)
                if made is not None and TRAFFIC_SPAN[0] <= made[0].x_at(t_s) <= TRAFFIC_SPAN[1]:
                    found.append(made)
        return found

    def quads_at(self, t_s: float) -> np.ndarray:
        """Every quad at t_s, float64 [Q, QUAD_FIELDS]: the street's, then the moving cars'."""
        parts = [self._street.quads]
        for car, quads in self._cars_at(_check_t(t_s)):
            moved = quads.copy()
            moved[:, 0] += car.x_at(t_s)
            parts.append(moved)
        return np.concatenate(parts)

    # ---------------------------------------------------------------- images
    def frame(self, t_s: float, c2w: np.ndarray | None = None) -> Frame:
        """The frame at t_s from ``c2w`` (default: the event camera's pose at t_s)."""
        c2w = self.camera_at(t_s) if c2w is None else c2w
        return render(self.quads_at(t_s), self._street.textures, c2w, self.intrinsics, SKY)

    def render(self, t_s: float) -> np.ndarray:
        """The event camera's sharp luminance at t_s: float64 [H, W] in [0, 1] (linear)."""
        return self.frame(t_s).luminance

    def render_novel(self, t_s: float) -> np.ndarray:
        """The novel camera's sharp luminance at t_s."""
        return self.frame(t_s, self.novel_camera_at(t_s)).luminance

    def static_frame(self, c2w: np.ndarray) -> Frame:
        """The street without its moving cars, from ``c2w``."""
        return render(self._street.quads, self._street.textures, c2w, self.intrinsics, SKY)

    def car_pixels(self, t_s: float, c2w: np.ndarray) -> np.ndarray:
        """[H, W] bool: the pixels whose centre sample shows a moving car at t_s from ``c2w``."""
        return self.frame(t_s, c2w).quad >= len(self._street.quads)  # the cars' quads follow the street's

    def car_windows(self, t_s: float, c2w: np.ndarray, margin: int = 3) -> list[tuple[int, int, int, int]]:
        """Pixel windows (x0, y0, x1, y1), ends excluded, that hold the moving cars seen from ``c2w`` at
        t_s, each widened by ``margin`` pixels (their edges' anti-aliasing reaches under a pixel)."""
        cars = self.cars_at(t_s)
        if not cars:
            return []
        size = np.array([[tx.CAR_MODELS[c.model].length, tx.CAR_MODELS[c.model].width,
                          tx.CAR_MODELS[c.model].body + tx.CAR_MODELS[c.model].cabin] for c in cars])
        low = np.array([[c.x_at(t_s), c.y, 0.0] for c in cars]) - 0.5 * size * [1, 1, 0]
        corners = low[:, None, :] + _CORNERS[None] * size[:, None, :]  # [C, 8, 3]
        cam = (corners - c2w[:3, 3]) @ c2w[:3, :3]
        a, b = cam[:, _EDGES[:, 0]], cam[:, _EDGES[:, 1]]  # the box's edges, clipped to the near plane
        cross = (a[..., 2] >= NEAR) != (b[..., 2] >= NEAR)
        w = np.where(cross, (NEAR - a[..., 2]) / np.where(cross, b[..., 2] - a[..., 2], 1.0), 0.0)
        points = np.concatenate([cam, a + w[..., None] * (b - a)], axis=1)
        seen = np.concatenate([cam[..., 2] >= NEAR, cross], axis=1)
        k = self.intrinsics
        z = np.where(seen, points[..., 2], 1.0)
        xs, ys = k.fx * points[..., 0] / z + k.cx, k.fy * points[..., 1] / z + k.cy
        windows = []
        for i in np.flatnonzero(seen.any(axis=1)):
            px, py = xs[i][seen[i]], ys[i][seen[i]]
            x0, x1 = max(0, math.floor(px.min()) - margin), min(self.width, math.ceil(px.max()) + margin + 1)
            y0, y1 = max(0, math.floor(py.min()) - margin), min(self.height, math.ceil(py.max()) + margin + 1)
            if x0 < x1 and y0 < y1:
                windows.append((x0, y0, x1, y1))
        return windows


_CORNERS = np.array([[i & 1, (i >> 1) & 1, (i >> 2) & 1] for i in range(8)], np.float64)
"""A unit box's corners: bit 0 is x, bit 1 y, bit 2 z."""
_EDGES = np.array([(i, i | bit) for i in range(8) for bit in (1, 2, 4) if not i & bit])
"""Its 12 edges: corners that differ in one bit."""


KEYFRAME_US = 4000
"""Interval of the static street's renders in ``EventRender`` (the event simulation's longest step)."""


class EventRender:
    """The event camera's luminance at t_us (an int, µs) for the event simulation, ``simulate_render``'s
    callback, at a fraction of a full frame's cost.

    The simulation renders every 0.25 to 4 ms, wherever some pixel changes by a threshold or more: the
    moving cars need that, the street seen by the walking camera does not (it moves by a tenth of a
    pixel in 2 ms). So the street without its cars is rendered every ``keyframe_us`` and interpolated
    linearly in between (what the simulator assumes of a pixel between two samples), and the moving
    cars' windows (``car_windows``; with a 2-pixel guard ring, rendered and left out) exactly at t.
    """

    GUARD = 2

    def __init__(self, scene: StreetScene, keyframe_us: int = KEYFRAME_US) -> None:
        if isinstance(keyframe_us, bool) or not isinstance(keyframe_us, int) or keyframe_us < 1:
            raise InvalidInputError(f"keyframe_us must be a positive integer, got {keyframe_us!r}")
        self.scene, self.keyframe_us = scene, keyframe_us
        self._keys: dict[int, np.ndarray] = {}
        self.renders = 0
        """Full frames rendered (the static keyframes)."""

    def _key(self, k: int) -> np.ndarray:
        if k not in self._keys:
            if len(self._keys) >= 3:
                del self._keys[max(self._keys, key=lambda j: abs(j - k))]
            c2w = self.scene.camera_at(k * self.keyframe_us * 1e-6)
            self._keys[k] = self.scene.static_frame(c2w).luminance
            self.renders += 1
        return self._keys[k]

    def __call__(self, t_us: int) -> np.ndarray:
        k, r = divmod(int(t_us), self.keyframe_us)
        a = self._key(k)
        img = a.copy() if r == 0 else a + (r / self.keyframe_us) * (self._key(k + 1) - a)
        t_s = t_us * 1e-6
        c2w = self.scene.camera_at(t_s)
        windows = self.scene.car_windows(t_s, c2w)
        if windows:
            h, w, g = self.scene.height, self.scene.width, self.GUARD
            mask = np.zeros((h, w), bool)  # the windows and their guard rings: every pasted pixel's
            for x0, y0, x1, y1 in windows:  # neighbours are rendered too
                mask[max(0, y0 - g):y1 + g, max(0, x0 - g):x1 + g] = True
            exact = render(self.scene.quads_at(t_s), self.scene._street.textures, c2w, self.scene.intrinsics,
                           SKY, mask).luminance
            for x0, y0, x1, y1 in windows:
                img[y0:y1, x0:x1] = exact[y0:y1, x0:x1]
        return img
