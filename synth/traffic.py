"""``traffic``: a street seen by a static (or slowly panning) camera, built by 2D image compositing.

Not Gaussians: the benchmark's other scenes are drawn by our own rasterizer, the representation the
model fits. Here the grey luminance image at any instant is composited analytically:

- the background: a street layout (sky and building facades with windows, pavements, curbs, a
  four-lane road with dashed and centre lines, a verge with tree canopies), smooth regions with
  anti-aliased edges and a multi-scale value-noise texture; luminance in [0.04, 0.8] (linear, never
  saturated);
- the objects: cars (10-20 px long, 5-9 px wide: a rounded body, windscreen, rear window, roof and a
  soft shadow) in four lanes, two each way, and bikes (5-7 px) on the lower pavement, crossing the
  frame at 100-400 px/s; every object enters and leaves the frame;
- the camera: identity pose by default; with ``pan_px_s`` it turns about its y axis at a constant
  angular speed pan_px_s / fx, so the centre pixel moves by fx * tan(theta(t)) ~ pan_px_s * t.

Geometry lives on a "canvas": the image plane of the camera at theta = 0, in full-resolution (346x260)
pixels, unbounded in both directions. A pure rotation maps the canvas to the current image by the
homography K R^T K^-1, so the panned frames are exact for any scene depth, and the recorded poses are
the true ones. Objects move along the canvas rows at a constant speed; traffic is a deterministic
function of (seed, lane, slot): each lane has one slot every ``period`` seconds, occupied with
probability ``occupancy``, so the scene is defined at every t, negative or past any duration.

Anti-aliasing: edges are signed distances turned into a one-output-pixel coverage ramp, noise octaves
finer than two output pixels are left out, positions are sub-pixel. A static camera evaluates the
background once at the pixel centres; a panning one samples a 4x supersampled canvas bilinearly.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from edmcgs.errors import InvalidInputError
from edmcgs.geometry import Intrinsics
from edmcgs.synth.orbit import DAVIS346
from edmcgs.synth.procedural import band, box_sd, fbm, hash01, ramp

FULL_WIDTH, FULL_HEIGHT = DAVIS346.width, DAVIS346.height
CANVAS_SUPERSAMPLING = 4
"""Canvas texels per output pixel along each axis (the panned background is sampled from it)."""

# canvas rows (full-resolution px) of the layout
SKY_BOTTOM = 26.0  # the tallest roof line
FACADE_BOTTOM = 66.0
UPPER_PAVEMENT = (70.0, 90.0)
ROAD = (92.0, 196.0)
LOWER_PAVEMENT = (197.0, 214.0)
LANE_LINES = (116.0, 172.0)  # dashed, between lanes of one direction
CENTRE_LINES = (142.5, 145.5)  # the double centre line
BLOCK_PX = 64.0  # width of a building block


@dataclass(frozen=True)
class Lane:
    """Objects move along canvas row ``v`` in ``direction`` (+1: to +u) at ``speed`` px/s."""

    v: float
    direction: int
    speed: float
    kind: str  # "car" or "bike"
    period_s: float
    """One slot per period; slot k's object passes u = 0 at (k + 0.5 * jitter) * period."""


@dataclass(frozen=True)
class MovingObject:
    """One car or bike; ``u_at(t)`` is its centre's canvas column at t (full-resolution px)."""

    lane: int
    slot: int
    kind: str
    t_pass: float
    """When the centre crosses canvas column 0."""
    u_speed: float
    """Signed px/s along the canvas row."""
    v: float
    """Canvas row of the centre."""
    length: float
    width: float
    body: float
    glass: float
    roof: float

    def u_at(self, t_s: float) -> float:
        return self.u_speed * (t_s - self.t_pass)


def background(u: np.ndarray, v: np.ndarray, seed: int, px: float) -> np.ndarray:
    """Luminance of the static street at canvas points (u, v) (full-resolution px), float64.

    px: canvas px per output pixel (1 at 346x260, 2 at 173x130): the width of the edge ramps.
    """
    key = 1000 * seed
    lo = fbm(u, v, (96.0, 48.0, 24.0), key + 1, px)  # large-scale shading
    hi = fbm(u, v, (8.0, 4.0, 2.0), key + 2, px)  # grain
    # sky and facades: one building per block, its own tone and roof line, a window grid
    block = np.floor(u / BLOCK_PX)
    bu = u - block * BLOCK_PX
    tone = 0.2 + 0.22 * hash01(block, 0, key + 3)
    roof = 4.0 + (SKY_BOTTOM - 4.0) * hash01(block, 1, key + 3)
    gap = ramp(-(np.abs(bu - 0.5 * BLOCK_PX) - (0.5 * BLOCK_PX - 1.5)), px)  # dark joint between blocks
    wu, wv = np.floor((bu - 4.0) / 12.0), np.floor((v - roof - 6.0) / 14.0)
    cu, cv = bu - 4.0 - 12.0 * wu - 6.0, v - roof - 6.0 - 14.0 * wv - 7.0
    in_grid = ((bu > 4.0) & (bu < BLOCK_PX - 4.0) & (v > roof + 6.0)
               & (v < FACADE_BOTTOM - 6.0)).astype(float)
    lit = hash01(block * 64 + wu, wv, key + 4)
    glass = np.where(lit > 0.8, 0.62, 0.07 + 0.08 * lit)
    window = in_grid * ramp(box_sd(cu, cv, 3.0, 4.0), px)
    facade = tone * (1 + 0.25 * lo + 0.12 * hi)
    facade = facade * (1 - 0.45 * gap)
    facade = facade + window * (glass - facade)
    facade = facade + band(v, FACADE_BOTTOM - 4.0, FACADE_BOTTOM + 1.0, px) * (0.13 - facade)  # plinth
    sky = 0.74 + 0.04 * lo - 0.0006 * v
    img = sky + ramp(roof - v, px) * (facade - sky)
    # pavements with joints, curbs with a bright top and a dark gutter
    pave = 0.4 * (1 + 0.12 * lo + 0.08 * hi)
    joints = np.maximum(ramp(np.abs(u - 16.0 * np.round(u / 16.0)) - 0.5, px),
                        ramp(np.abs(v - 80.0) - 0.5, px)) * 0.2
    joints += ramp(np.abs(v - 205.5) - 0.5, px) * 0.2
    pave = pave * (1 - joints)
    img = img + band(v, FACADE_BOTTOM + 1.0, UPPER_PAVEMENT[1], px) * (pave - img)
    img = img + band(v, LOWER_PAVEMENT[0], LOWER_PAVEMENT[1], px) * (pave - img)
    img = img + band(v, UPPER_PAVEMENT[1], ROAD[0], px) * (0.56 * (1 + 0.05 * hi) - img)
    img = img + band(v, ROAD[1], LOWER_PAVEMENT[0], px) * (0.52 * (1 + 0.05 * hi) - img)
    # the road: asphalt, repair patches, lane markings
    patch = np.clip(4.0 * (fbm(u, v, (40.0, 20.0), key + 5, px) - 0.25), 0.0, 1.0)
    asphalt = 0.19 * (1 + 0.18 * lo + 0.16 * hi) * (1 - 0.25 * patch)
    dash = ramp(np.abs(u - 28.0 * np.round(u / 28.0)) - 7.0, px)
    for line in LANE_LINES:
        asphalt = asphalt + dash * ramp(np.abs(v - line) - 0.75, px) * (0.6 - asphalt)
    for line in CENTRE_LINES:
        asphalt = asphalt + ramp(np.abs(v - line) - 0.6, px) * (0.5 - asphalt)
    img = img + band(v, ROAD[0] + 1.0, ROAD[1] - 1.0, px) * (asphalt - img)
    img = img + band(v, ROAD[0], ROAD[0] + 2.0, px) * (0.09 - img)  # gutter shadow under the curb
    # the verge: grass and tree canopies
    canopy = np.clip(3.0 * (fbm(u, v, (48.0, 24.0, 12.0), key + 6, px) + 0.05), 0.0, 1.0)
    grass = 0.2 * (1 + 0.3 * lo + 0.25 * hi)
    trees = 0.07 * (1 + 0.6 * hi + 0.3 * lo)
    verge = grass + canopy * (trees - grass)
    img = img + ramp(LOWER_PAVEMENT[1] - v, px) * (verge - img)
    return np.clip(img, 0.02, 0.85)


def _check_t(t_s) -> float:
    t_s = float(t_s)
    if not math.isfinite(t_s):
        raise InvalidInputError(f"t_s must be a finite time in seconds, got {t_s!r}")
    return t_s


class TrafficScene:
    """The street at ``width`` x ``height`` (DAVIS346 intrinsics scaled), seeded.

    pan_px_s: 0 for a static camera, else the pan speed at the image centre (full-resolution px/s; the
    camera turns about its y axis at pan_px_s / fx rad/s, the scene moving to the left).
    occupancy: probability that a lane's slot holds an object (traffic density).
    """

    def __init__(self, width: int = FULL_WIDTH, height: int = FULL_HEIGHT, *, pan_px_s: float = 0.0,
                 seed: int = 0, occupancy: float = 0.85) -> None:
        for name, value, lo, hi in (("width", width, 8, 4096), ("height", height, 8, 4096)):
            if isinstance(value, bool) or not isinstance(value, int | np.integer) or not lo <= value <= hi:
                raise InvalidInputError(f"{name} must be an integer in {lo}..{hi}, got {value!r}")
        if not (isinstance(pan_px_s, int | float) and math.isfinite(pan_px_s) and abs(pan_px_s) <= 200):
            raise InvalidInputError(f"pan_px_s must be a finite speed within +-200 px/s, got {pan_px_s!r}")
        if isinstance(seed, bool) or not isinstance(seed, int | np.integer) or not 0 <= seed < 2**31:
            raise InvalidInputError(f"seed must be an integer in 0..2**31-1, got {seed!r}")
        if not (isinstance(occupancy, int | float) and 0 <= occupancy <= 1):
            raise InvalidInputError(f"occupancy must be in [0, 1], got {occupancy!r}")
        self.name = "traffic-pan" if pan_px_s else "traffic"
        self.width, self.height = int(width), int(height)
        self.seed, self.pan_px_s, self.occupancy = int(seed), float(pan_px_s), float(occupancy)
        self.intrinsics: Intrinsics = DAVIS346.scaled(self.width, self.height)
        self.px = FULL_WIDTH / self.width  # canvas px per output pixel (horizontally)
        rng = np.random.default_rng(np.random.SeedSequence([self.seed, 7]))
        lanes = []
        for v, direction in ((104.0, 1), (128.0, 1), (160.0, -1), (184.0, -1)):
            speed = float(rng.uniform(110.0, 390.0))
            lanes.append(Lane(v, direction, speed, "car", FULL_WIDTH / (2.5 * speed)))
        speed = float(rng.uniform(100.0, 150.0))
        lanes.append(Lane(205.5, int(rng.choice([-1, 1])), speed, "bike", FULL_WIDTH / (1.2 * speed)))
        self.lanes = tuple(lanes)
        self._objects: dict[tuple[int, int], MovingObject | None] = {}
        self._static_uv = self._uv(0.0) if not self.pan_px_s else None
        self._static_bg = (None if self._static_uv is None
                           else background(*self._static_uv, self.seed, self.px))
        self._canvas: tuple[np.ndarray, float, float, float] | None = None  # image, u0, v0, step

    # ---------------------------------------------------------------- camera
    def theta(self, t_s: float) -> float:
        """Pan angle at t_s (rad, about the camera's y axis; 0 at t = 0)."""
        return self.pan_px_s / DAVIS346.fx * _check_t(t_s)

    def camera_at(self, t_s: float) -> np.ndarray:
        """Camera-to-world float64 [4, 4] (OpenCV convention): a rotation about y, at the origin."""
        th = self.theta(t_s)
        c, s = math.cos(th), math.sin(th)
        c2w = np.eye(4)
        c2w[:3, :3] = [[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]]
        return c2w

    def _uv(self, t_s: float) -> tuple[np.ndarray, np.ndarray]:
        """Canvas coordinates (full-resolution px) of every output pixel centre at t_s: [H, W] each."""
        k = self.intrinsics
        a = (np.arange(self.width) - k.cx) / k.fx
        b = (np.arange(self.height) - k.cy) / k.fy
        th = self.theta(t_s)
        c, s = math.cos(th), math.sin(th)
        dz = c - s * a  # [W]
        u = DAVIS346.fx * (c * a + s) / dz + DAVIS346.cx
        v = DAVIS346.fy * b[:, None] / dz[None, :] + DAVIS346.cy
        return np.broadcast_to(u[None, :], v.shape), v

    def to_image(self, t_s: float, u, v) -> tuple[np.ndarray, np.ndarray]:
        """Output-pixel coordinates (x, y) of canvas points (u, v) at t_s (the inverse of ``_uv``)."""
        th = self.theta(t_s)
        c, s = math.cos(th), math.sin(th)
        wx = (np.asarray(u, float) - DAVIS346.cx) / DAVIS346.fx
        wy = (np.asarray(v, float) - DAVIS346.cy) / DAVIS346.fy
        cx, cz = c * wx - s, s * wx + c  # R^T applied to (wx, wy, 1)
        k = self.intrinsics
        return k.fx * cx / cz + k.cx, k.fy * wy / cz + k.cy

    # ---------------------------------------------------------------- background
    def _background(self, uv) -> np.ndarray:
        if self._static_bg is not None:
            return self._static_bg.copy()
        u, v = uv
        self._ensure_canvas(float(u.min()), float(u.max()), float(v.min()), float(v.max()))
        img, u0, v0, step = self._canvas
        x, y = (u - u0) / step, (v - v0) / step
        ix, iy = np.floor(x).astype(np.int64), np.floor(y).astype(np.int64)
        fx, fy = x - ix, y - iy
        w = img.shape[1]
        flat = img.ravel()
        i00 = iy * w + ix
        top = flat[i00] * (1 - fx) + flat[i00 + 1] * fx
        bottom = flat[i00 + w] * (1 - fx) + flat[i00 + w + 1] * fx
        return top * (1 - fy) + bottom * fy

    def _ensure_canvas(self, u_lo, u_hi, v_lo, v_hi) -> None:
        """(Re)build the supersampled canvas so that it covers [u_lo, u_hi] x [v_lo, v_hi], with a
        margin (rebuilt rarely; texel (i, j) is always the point (j * step, i * step), so a rebuild
        gives the same values wherever it starts)."""
        step = self.px / CANVAS_SUPERSAMPLING
        if self._canvas is not None:
            img, u0, v0, _ = self._canvas
            u1, v1 = u0 + (img.shape[1] - 2) * step, v0 + (img.shape[0] - 2) * step
            if u0 <= u_lo and u_hi <= u1 and v0 <= v_lo and v_hi <= v1:
                return
            u_lo, u_hi, v_lo, v_hi = min(u_lo, u0), max(u_hi, u1), min(v_lo, v0), max(v_hi, v1)
        margin_u, margin_v = 48.0, 8.0
        j0, j1 = math.floor((u_lo - margin_u) / step), math.ceil((u_hi + margin_u) / step) + 2
        i0, i1 = math.floor((v_lo - margin_v) / step), math.ceil((v_hi + margin_v) / step) + 2
        us, vs = step * np.arange(j0, j1), step * np.arange(i0, i1)
        img = np.empty((len(vs), len(us)))
        for r in range(0, len(vs), 256):  # in bands, to bound the temporaries
            uu, vv = np.meshgrid(us, vs[r:r + 256])
            img[r:r + 256] = background(uu, vv, self.seed, self.px)
        self._canvas = (img, j0 * step, i0 * step, step)

    # ---------------------------------------------------------------- objects
    def _object(self, lane_index: int, slot: int) -> MovingObject | None:
        key = (lane_index, slot)
        if key not in self._objects:
            lane = self.lanes[lane_index]
            rng = np.random.default_rng(np.random.SeedSequence([self.seed, 11, lane_index, slot + 2**40]))
            draw = rng.random(12)
            obj = None
            if draw[0] < self.occupancy:
                t_pass = (slot + 0.5 * draw[1]) * lane.period_s
                if lane.kind == "car":
                    length, width = 10.0 + 10.0 * draw[2], 0.0
                    width = min(5.0 + 4.0 * draw[3], 0.62 * length)
                    tone = draw[4]
                    body = (0.05 + 0.08 * draw[5] if tone < 0.35 else
                            0.25 + 0.15 * draw[5] if tone < 0.65 else 0.58 + 0.2 * draw[5])
                    glass, roof = 0.04 + 0.05 * draw[6], min(0.85, body * (1.08 + 0.1 * draw[7]) + 0.02)
                    offset = 3.0 * (draw[8] - 0.5)
                else:
                    length, width = 5.0 + 2.0 * draw[2], 3.0 + 1.0 * draw[3]
                    body = 0.06 + 0.3 * draw[5] if draw[4] < 0.6 else 0.6 + 0.15 * draw[5]
                    glass, roof, offset = body, body, 2.0 * (draw[8] - 0.5)
                obj = MovingObject(lane_index, slot, lane.kind, t_pass, lane.direction * lane.speed,
                                   lane.v + offset, length, width, body, glass, roof)
            self._objects[key] = obj
        return self._objects[key]

    def objects_at(self, t_s: float, margin_px: float = 0.0) -> list[MovingObject]:
        """The objects whose box reaches within ``margin_px`` (canvas px) of the frame at t_s."""
        t_s = _check_t(t_s)
        corners_u = self._uv(t_s)[0][0, [0, -1]]
        u_lo, u_hi = float(corners_u.min()) - margin_px - 30.0, float(corners_u.max()) + margin_px + 30.0
        found = []
        for i, lane in enumerate(self.lanes):
            # u(t) = d * speed * (t - t_pass) in [u_lo, u_hi]  <=>  t_pass in [t - hi/(d s), t - lo/(d s)]
            velocity = lane.direction * lane.speed
            ends = sorted((t_s - u_lo / velocity, t_s - u_hi / velocity))
            k0 = math.floor(ends[0] / lane.period_s) - 1
            k1 = math.ceil(ends[1] / lane.period_s) + 1
            for k in range(k0, k1 + 1):
                obj = self._object(i, k)
                if obj is not None and u_lo <= obj.u_at(t_s) <= u_hi:
                    found.append(obj)
        return found

    def _draw(self, img, uv, t_s, obj, coverage=None) -> None:
        """Composite one object into img (and its body coverage into ``coverage``)."""
        px = self.px
        cu = obj.u_at(t_s)
        reach_u, reach_v = 0.5 * obj.length + 3.0 * px, 0.5 * obj.width + 3.0 * px
        top, bottom = obj.v - reach_v, obj.v + reach_v + 2.0  # + the shadow
        xs, ys = self.to_image(t_s, [cu - reach_u, cu + reach_u, cu - reach_u, cu + reach_u],
                               [top, top, bottom, bottom])
        x0, x1 = max(0, math.floor(xs.min()) - 1), min(self.width, math.ceil(xs.max()) + 2)
        y0, y1 = max(0, math.floor(ys.min()) - 1), min(self.height, math.ceil(ys.max()) + 2)
        if x0 >= x1 or y0 >= y1:
            return
        u, v = uv[0][y0:y1, x0:x1], uv[1][y0:y1, x0:x1]
        a = (u - cu) * (1.0 if obj.u_speed >= 0 else -1.0)  # along the motion, front > 0
        b = v - obj.v
        hl, hw = 0.5 * obj.length, 0.5 * obj.width
        radius = min(2.0, 0.6 * hw) if obj.kind == "car" else hw
        shadow = np.clip(0.5 - box_sd(a + 0.5, b - 1.6, hl + 0.3, hw + 0.3, radius) / (1.8 * px), 0.0, 1.0)
        body = ramp(box_sd(a, b, hl, hw, radius), px)
        lum = np.full(a.shape, obj.body)
        if obj.kind == "car":
            roof = ramp(box_sd(a + 0.05 * obj.length, b, 0.2 * obj.length, hw - 1.2, 0.8), px)
            lum += roof * (obj.roof - lum)
            front = ramp(box_sd(a - 0.2 * obj.length, b, 0.07 * obj.length + 0.5, hw - 0.9, 0.5), px)
            rear = ramp(box_sd(a + 0.3 * obj.length, b, 0.05 * obj.length + 0.4, hw - 1.1, 0.5), px)
            lum += np.maximum(front, rear) * (obj.glass - lum)
        region = img[y0:y1, x0:x1]
        region *= 1.0 - 0.5 * shadow
        region += body * (lum - region)
        if coverage is not None:
            coverage[y0:y1, x0:x1] = np.maximum(coverage[y0:y1, x0:x1], body)

    # ---------------------------------------------------------------- images
    def render(self, t_s: float) -> np.ndarray:
        """The sharp luminance at t_s: float64 [H, W] in [0, 1] (linear, never saturated)."""
        t_s = _check_t(t_s)
        uv = self._static_uv if self._static_uv is not None else self._uv(t_s)
        img = self._background(uv)
        for obj in self.objects_at(t_s):
            self._draw(img, uv, t_s, obj)
        return img

    def render_with_coverage(self, t_s: float) -> tuple[np.ndarray, np.ndarray]:
        """(render(t_s), the moving objects' coverage in [0, 1]): float64 [H, W] each."""
        t_s = _check_t(t_s)
        uv = self._static_uv if self._static_uv is not None else self._uv(t_s)
        img = self._background(uv)
        cov = np.zeros_like(img)
        for obj in self.objects_at(t_s):
            self._draw(img, uv, t_s, obj, cov)
        return img, cov
