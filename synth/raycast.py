"""A small ray caster of textured quads (planes and boxes): grey images of scenes not made of Gaussians.

Geometry is quads: an ``origin`` corner and two orthogonal edges, ``a`` (texture u, "right" as seen from
the front) and ``b`` (texture v, "down"); the front is the side of the normal b x a, and only fronts are
drawn (a box is its outward faces; ``box`` builds one, rotated about z or not). A quad's texture
coordinates are metres from its origin plus its ``uv`` offset; the texture maps them at its own
``texel_m`` metres per texel and repeats.

A frame, for a pinhole camera (OpenCV axes, pixel centres at integer coordinates):

1. visibility at the pixel centres: every quad facing the camera is clipped to the near plane and
   projected; its pixels (the projected polygon's row spans, widened by a pixel) are ray-tested in the
   camera frame, and the nearest hit kept;
2. shading at the centres: the quad's ``shade`` factor times its texture filtered over the pixel's
   footprint (the analytic derivatives of the hit point): mip-mapped and anisotropic (two trilinear taps
   along the footprint's long axis), and continuous in the footprint, so that a texture seen at a
   grazing angle neither aliases nor flickers as the camera moves; no hit: the sky, a gradient over
   elevation;
3. anti-aliasing, continuous in the geometry: a pixel whose centre sees another quad (or the sky) than
   one of its 8 neighbours, whose centre's hit is within ``AA_REACH`` pixels of its quad's border, or
   that a sliver (a quad under ``THIN_PX`` across) touches, is resolved at ``SAMPLES`` sub-samples (a
   rotated grid). At each, every quad reaching the pixel covers it softly (a linear ramp as wide as the
   sub-sample spacing across each of its projected edges: an edge moving by a hundredth of a pixel
   changes the pixel by about a hundredth of its contrast, never by a step), and the quads are taken
   nearest first (their depths at that sub-sample), each the share of the area still free; the pixel
   is the share-weighted mean of the quads it sees, each shaded once at the centroid of its shares.

Point-sampled coverage (binary sub-samples) would move an edge across a pixel in steps, and a dark
pixel would jump by many contrast thresholds at once: events from aliasing, and an event simulation
that must halve its steps forever. Here a step remains only where two surfaces meet at a contact line
(a bollard on the pavement): their order flips at one sub-sample at a time. The ramps' price: where
three faces of a box meet, their ramps leave the background a share of the pixel there (a faint dot,
up to a quarter of it), which moves with the corner as smoothly as the rest.

No lighting beyond the per-quad factor, no shadows, no transparency: a grey street with motion in it,
whose every edge and texture is band-limited, so that the events a moving camera sees come from the
scene and not from sampling.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba as nb
import numpy as np

from edmcgs.errors import InvalidInputError
from edmcgs.geometry import Intrinsics, validate_pose

QUAD_FIELDS = 13
"""A quad's row: origin (3), a (3), b (3), texture id, u offset, v offset (metres), shade."""
SAMPLES = 4
"""Sub-samples of an anti-aliased pixel."""
MAXC = 12
"""Most quads composited in one anti-aliased pixel (the nearest)."""
AA_REACH = 0.8
"""A pixel is anti-aliased when its centre's hit is within this many pixels of its quad's border (the
farthest sub-sample and its coverage ramp reach 0.78 px, ``_SUB_REACH``)."""
NEAR = 1e-3
"""Near clipping plane, metres."""
THIN_PX = 3.0
"""A quad narrower than this across a row (or in height) is a sliver: every pixel it touches is
anti-aliased, since pixel centres alone could miss it."""

# rotated grid: offset k = ((k + 0.5) / 4, ((3 k) mod 4 + 0.5) / 4) - 0.5, every x and y distinct
_SUB_X = (np.arange(SAMPLES) + 0.5) / SAMPLES - 0.5
_SUB_Y = ((3 * np.arange(SAMPLES)) % SAMPLES + 0.5) / SAMPLES - 0.5
_SUB_REACH = float(np.hypot(_SUB_X, _SUB_Y).max() + 0.5 / np.sqrt(SAMPLES))
"""The farthest a quad's polygon may be from a pixel's centre and still cover one of its sub-samples:
the farthest sub-sample and half a coverage ramp."""
_FAST = {"nsz", "arcp", "contract", "afn", "reassoc"}
"""numba's fast-math flags short of assuming no NaN and no infinity (the depth buffers start at inf)."""
_SCALE = 0.5 ** np.arange(64.0)
"""Texel coordinates of level l = level 0's times _SCALE[l]."""


# --------------------------------------------------------------------------------------------- textures

@dataclass(frozen=True)
class Textures:
    """Grey textures with their mip pyramids, in one flat array (power-of-two sizes: they repeat).

    data: float32 [N]; table: int64 [T, L, 3] (offset, width, height) of each level; levels: int64 [T];
    texel_m: float64 [T], metres per texel of level 0.
    """

    data: np.ndarray
    table: np.ndarray
    levels: np.ndarray
    texel_m: np.ndarray

    @classmethod
    def build(cls, images: list[tuple[np.ndarray, float]]) -> Textures:
        """From (image [H, W] in [0, 1], metres per texel) pairs; H and W powers of two."""
        if not images:
            raise InvalidInputError("Textures.build needs at least one image")
        pyramids = []
        for i, (image, texel) in enumerate(images):
            img = np.asarray(image, np.float64)
            h, w = img.shape if img.ndim == 2 else (0, 0)
            if img.ndim != 2 or h < 1 or w < 1 or h & (h - 1) or w & (w - 1):
                raise InvalidInputError(f"texture {i} must be [H, W] with H and W powers of two, "
                                        f"got shape {img.shape}")
            if not np.isfinite(img).all():
                raise InvalidInputError(f"texture {i} holds NaN or Inf")
            if not (math.isfinite(texel) and texel > 0):
                raise InvalidInputError(f"texture {i}: texel size must be > 0 metres, got {texel!r}")
            levels = [img]
            while min(levels[-1].shape) > 1:  # a 2x2 box per level: every level halves both sides
                t = levels[-1]
                levels.append(0.25 * (t[0::2, 0::2] + t[1::2, 0::2] + t[0::2, 1::2] + t[1::2, 1::2]))
            pyramids.append(levels)
        depth = max(len(p) for p in pyramids)
        table = np.zeros((len(pyramids), depth, 3), np.int64)
        chunks, offset = [], 0
        for i, levels in enumerate(pyramids):
            for j, level in enumerate(levels):
                table[i, j] = (offset, level.shape[1], level.shape[0])
                chunks.append(level.astype(np.float32).ravel())
                offset += level.size
        return cls(np.concatenate(chunks), table, np.array([len(p) for p in pyramids], np.int64),
                   np.array([t for _, t in images], np.float64))

    def __len__(self) -> int:
        return len(self.levels)


# --------------------------------------------------------------------------------------------- geometry

def quad(origin, a, b, texture: int, shade: float = 1.0, uv=(0.0, 0.0)) -> np.ndarray:
    """One quad's row (see ``QUAD_FIELDS``): corner ``origin``, edges ``a`` (u) and ``b`` (v), orthogonal."""
    origin, a, b = (np.asarray(v, np.float64) for v in (origin, a, b))
    la, lb = np.linalg.norm(a), np.linalg.norm(b)
    if la <= 0 or lb <= 0 or abs(a @ b) > 1e-9 * la * lb:
        raise InvalidInputError(f"a quad's edges must be non-zero and orthogonal, got a={a}, b={b}")
    return np.concatenate([origin, a, b, [float(texture), float(uv[0]), float(uv[1]), float(shade)]])


BOX_FACES = ("+x", "-x", "+y", "-y", "top", "bottom")


def box(centre, size, faces: dict, *, yaw: float = 0.0, light=None, ambient: float = 0.5) -> np.ndarray:
    """The faces of a box as quads [K, QUAD_FIELDS].

    centre: (x, y, z) of the bottom face's centre; size: (length along its x, width along its y, height);
    yaw: rotation about z, radians. faces: {name: (texture, tone[, (u, v) offset])} for the faces to draw
    (``BOX_FACES``, in the box's own axes). Each face is textured as seen from outside: upright, u to the
    right, v down from its top edge (the top face: u along x, v along -y). Its shade is its tone, times
    ``ambient + (1 - ambient) * max(0, normal . light)`` when ``light`` (a unit vector towards the
    light) is given.
    """
    c, s = math.cos(yaw), math.sin(yaw)
    ex, ey, ez = np.array([c, s, 0.0]), np.array([-s, c, 0.0]), np.array([0.0, 0.0, 1.0])
    lx, ly, lz = (float(v) for v in size)
    mid = np.asarray(centre, np.float64) + 0.5 * lz * ez
    rows = []
    for name, spec in faces.items():
        if name not in BOX_FACES:
            raise InvalidInputError(f"box face {name!r} is unknown; choose among {', '.join(BOX_FACES)}")
        texture, tone = spec[0], spec[1]
        uv = spec[2] if len(spec) > 2 else (0.0, 0.0)
        if name in ("top", "bottom"):
            sign = 1.0 if name == "top" else -1.0
            normal = sign * ez
            a, b = lx * ex, -sign * ly * ey
            origin = mid + sign * 0.5 * lz * ez - 0.5 * a - 0.5 * b
        else:
            axis = {"+x": ex, "-x": -ex, "+y": ey, "-y": -ey}[name]
            half = 0.5 * (lx if name in ("+x", "-x") else ly)
            width = ly if name in ("+x", "-x") else lx
            normal = axis
            right = np.cross(-normal, ez)
            a, b = width * right, -lz * ez
            origin = mid + half * normal - 0.5 * a - 0.5 * b
        shade = tone
        if light is not None:
            shade = tone * (ambient + (1.0 - ambient) * max(0.0, float(normal @ np.asarray(light))))
        rows.append(quad(origin, a, b, texture, shade, uv))
    return np.array(rows).reshape(-1, QUAD_FIELDS)


# --------------------------------------------------------------------------------------------- kernels

@nb.njit(cache=True, inline="always", error_model="numpy", fastmath=_FAST)
def _bilinear(data, off, w, h, u, v):  # pragma: no cover - compiled
    """Repeating bilinear lookup at (u, v) texels of one level (texel i spans [i, i + 1))."""
    x, y = u - 0.5, v - 0.5
    fx0, fy0 = math.floor(x), math.floor(y)
    fx, fy = x - fx0, y - fy0
    ix0, iy0 = int(fx0) & (w - 1), int(fy0) & (h - 1)
    ix1, iy1 = (ix0 + 1) & (w - 1), (iy0 + 1) & (h - 1)
    r0, r1 = off + iy0 * w, off + iy1 * w
    top = data[r0 + ix0] + (data[r0 + ix1] - data[r0 + ix0]) * fx
    bottom = data[r1 + ix0] + (data[r1 + ix1] - data[r1 + ix0]) * fx
    return top + (bottom - top) * fy


@nb.njit(cache=True, inline="always", error_model="numpy", fastmath=_FAST)
def _log2(x):  # pragma: no cover - compiled
    """log2(x) for x > 0, exact at powers of two and linear between: continuous, and cheap."""
    m, e = math.frexp(x)  # x = m 2^e, m in [0.5, 1)
    return e - 2.0 + 2.0 * m


@nb.njit(cache=True, inline="always", error_model="numpy", fastmath=_FAST)
def _filtered(data, table, levels, tex, u, v, ux, vx, uy, vy):  # pragma: no cover - compiled
    """The texture averaged over a pixel's footprint: (ux, vx), (uy, vy) = d(u, v)/dx, d(u, v)/dy in
    level-0 texels. Two trilinear taps along the footprint's long axis, a quarter of its length either
    side of the centre, each as wide as half of it (or its short axis, if wider); as the footprint turns
    round (axes ratio 2 to 1), the taps slide together and the width grows to the long axis: every
    change is continuous, so the filtered value never jumps as the camera moves."""
    lx, ly = ux * ux + vx * vx, uy * uy + vy * vy
    if lx >= ly:
        major, minor, au, av = math.sqrt(lx), math.sqrt(ly), ux, vx
    else:
        major, minor, au, av = math.sqrt(ly), math.sqrt(lx), uy, vy
    spread = min(1.0, max(0.0, major / max(minor, 1e-300) - 1.0))  # 0 isotropic .. 1 at a 2:1 ratio
    width = max(minor, major / (1.0 + spread))
    k = 0.25 * spread
    taps = 2 if spread >= 0.05 else 1
    if taps == 1:
        k = 0.0
    last = levels[tex] - 1
    lod = _log2(width) if width > 1.0 else 0.0
    l0 = min(int(lod), last)
    f = min(lod - l0, 1.0) if l0 < last else 0.0
    total = 0.0
    for t in range(taps):
        du, dv = (k if t == 0 else -k) * au, (k if t == 0 else -k) * av
        s = _SCALE[l0]
        a = _bilinear(data, table[tex, l0, 0], table[tex, l0, 1], table[tex, l0, 2],
                      (u + du) * s, (v + dv) * s)
        if f > 0.0:
            s *= 0.5
            b = _bilinear(data, table[tex, l0 + 1, 0], table[tex, l0 + 1, 1], table[tex, l0 + 1, 2],
                          (u + du) * s, (v + dv) * s)
            a += (b - a) * f
        total += a
    return total / taps


@nb.njit(cache=True, inline="always", error_model="numpy", fastmath=_FAST)
def _shade(cam, quads, data, table, levels, texel, q, x, y, fx, fy, cx, cy):  # pragma: no cover
    """(luminance, whether the hit is within AA_REACH pixels of the quad's border) of quad q at pixel
    (x, y)."""
    rx, ry = (x - cx) / fx, (y - cy) / fy
    ax, ay, az = cam[q, 3], cam[q, 4], cam[q, 5]
    bx, by, bz = cam[q, 6], cam[q, 7], cam[q, 8]
    den = rx * cam[q, 9] + ry * cam[q, 10] + cam[q, 11]
    inv = 1.0 / min(den, -1e-12)
    lam = cam[q, 12] * inv
    ra, rb = rx * ax + ry * ay + az, rx * bx + ry * by + bz
    u, v = lam * ra - cam[q, 15], lam * rb - cam[q, 16]  # metres along a and b from the origin
    # the footprint: dP/dx = lam / fx * (e_x - n_x / den * r), the same for y
    kx, ky, nx, ny = lam / fx, lam / fy, cam[q, 9] * inv, cam[q, 10] * inv
    ux, vx = kx * (ax - nx * ra), kx * (bx - nx * rb)
    uy, vy = ky * (ay - ny * ra), ky * (by - ny * rb)
    mu, mv = min(u, cam[q, 13] - u), min(v, cam[q, 14] - v)  # metres to the border, along a and b
    near = (mu < 0.0 or mu * mu < AA_REACH * AA_REACH * (ux * ux + uy * uy)
            or mv < 0.0 or mv * mv < AA_REACH * AA_REACH * (vx * vx + vy * vy))
    tex = int(quads[q, 9])
    s = 1.0 / texel[tex]
    lum = _filtered(data, table, levels, tex, (u + quads[q, 10]) * s, (v + quads[q, 11]) * s,
                    ux * s, vx * s, uy * s, vy * s)
    return quads[q, 12] * lum, near


@nb.njit(cache=True, inline="always", error_model="numpy", fastmath=_FAST)
def _sky(x, y, up, fx, fy, cx, cy, horizon, zenith):  # pragma: no cover - compiled
    rx, ry = (x - cx) / fx, (y - cy) / fy
    el = (rx * up[0] + ry * up[1] + up[2]) / math.sqrt(rx * rx + ry * ry + 1.0)
    return zenith + (horizon - zenith) * math.exp(-3.0 * max(el, 0.0))


@nb.njit(cache=True, inline="always", error_model="numpy", fastmath=_FAST)
def _span(poly, q, n, y, m):  # pragma: no cover - compiled
    """x extent (lo, hi) of convex polygon q (n vertices) within the rows [y - m, y + m]; lo > hi: none."""
    lo, hi = np.inf, -np.inf
    y0, y1 = y - m, y + m
    for i in range(n):
        vx, vy = poly[q, i, 0], poly[q, i, 1]
        if y0 <= vy <= y1:
            lo, hi = min(lo, vx), max(hi, vx)
        j = i + 1 if i + 1 < n else 0
        wx, wy = poly[q, j, 0], poly[q, j, 1]
        if vy != wy:
            if (vy - y0) * (wy - y0) <= 0.0:
                xx = vx + (y0 - vy) / (wy - vy) * (wx - vx)
                lo, hi = min(lo, xx), max(hi, xx)
            if (vy - y1) * (wy - y1) <= 0.0:
                xx = vx + (y1 - vy) / (wy - vy) * (wx - vx)
                lo, hi = min(lo, xx), max(hi, xx)
    return lo, hi


@nb.njit(cache=True, inline="always", error_model="numpy", fastmath=_FAST)
def _rotate(rot, v0, v1, v2, out):  # pragma: no cover - compiled
    for i in range(3):
        out[i] = rot[i, 0] * v0 + rot[i, 1] * v1 + rot[i, 2] * v2


@nb.njit(cache=True, error_model="numpy", fastmath=_FAST)
def _setup(quads, rot, centre, fx, fy, cx, cy, width, height, cam, poly, npoly, yr,
           edges):  # pragma: no cover - compiled
    """Each quad in the camera frame (cam), its projected polygon clipped to the near plane (poly,
    npoly; 0 when culled: facing away, edge-on, behind or off the image), its row range (yr) and its
    edges' functions (edges: A x + B y + C, the signed distance in pixels, positive inside)."""
    corners = np.empty((4, 3))
    clipped = np.empty((8, 3))
    o, a, b = np.empty(3), np.empty(3), np.empty(3)
    for q in range(quads.shape[0]):
        npoly[q] = 0
        _rotate(rot, quads[q, 0] - centre[0], quads[q, 1] - centre[1], quads[q, 2] - centre[2], o)
        _rotate(rot, quads[q, 3], quads[q, 4], quads[q, 5], a)
        _rotate(rot, quads[q, 6], quads[q, 7], quads[q, 8], b)
        la = math.sqrt(a[0] * a[0] + a[1] * a[1] + a[2] * a[2])
        lb = math.sqrt(b[0] * b[0] + b[1] * b[1] + b[2] * b[2])
        ah, bh = a / la, b / lb
        n0 = bh[1] * ah[2] - bh[2] * ah[1]  # n = b x a: the front side
        n1 = bh[2] * ah[0] - bh[0] * ah[2]
        n2 = bh[0] * ah[1] - bh[1] * ah[0]
        big_n = o[0] * n0 + o[1] * n1 + o[2] * n2
        if big_n >= 0.0:  # the camera is behind (or in) the quad's plane
            continue
        cam[q, 0:3], cam[q, 3:6], cam[q, 6:9] = o, ah, bh
        cam[q, 9], cam[q, 10], cam[q, 11], cam[q, 12] = n0, n1, n2, big_n
        cam[q, 13], cam[q, 14] = la, lb
        cam[q, 15] = o[0] * ah[0] + o[1] * ah[1] + o[2] * ah[2]
        cam[q, 16] = o[0] * bh[0] + o[1] * bh[1] + o[2] * bh[2]
        corners[0], corners[1], corners[2], corners[3] = o, o + a, o + a + b, o + b
        k = 0
        for i in range(4):
            p, r = corners[i], corners[(i + 1) % 4]
            if p[2] >= NEAR:
                clipped[k] = p
                k += 1
            if (p[2] >= NEAR) != (r[2] >= NEAR):
                clipped[k] = p + (NEAR - p[2]) / (r[2] - p[2]) * (r - p)
                k += 1
        if k < 3:
            continue
        x0, x1, y0, y1 = np.inf, -np.inf, np.inf, -np.inf
        for i in range(k):
            px = fx * clipped[i, 0] / clipped[i, 2] + cx
            py = fy * clipped[i, 1] / clipped[i, 2] + cy
            poly[q, i, 0], poly[q, i, 1] = px, py
            x0, x1, y0, y1 = min(x0, px), max(x1, px), min(y0, py), max(y1, py)
        if x1 < -1.0 or x0 > width or y1 < -1.0 or y0 > height:
            continue
        area = 0.0
        for i in range(k):
            j = i + 1 if i + 1 < k else 0
            area += poly[q, i, 0] * poly[q, j, 1] - poly[q, j, 0] * poly[q, i, 1]
        if abs(area) < 1e-9:  # edge-on
            continue
        sign = 1.0 if area > 0.0 else -1.0
        for i in range(k):
            j = i + 1 if i + 1 < k else 0
            dx, dy = poly[q, j, 0] - poly[q, i, 0], poly[q, j, 1] - poly[q, i, 1]
            length = math.sqrt(dx * dx + dy * dy)
            if length < 1e-12:
                edges[q, i, 0], edges[q, i, 1], edges[q, i, 2] = 0.0, 0.0, 1e9
                continue
            edges[q, i, 0] = -sign * dy / length
            edges[q, i, 1] = sign * dx / length
            edges[q, i, 2] = sign * (dy * poly[q, i, 0] - dx * poly[q, i, 1]) / length
        npoly[q] = k
        yr[q, 0], yr[q, 1] = y0, y1


@nb.njit(cache=True, inline="always", error_model="numpy", fastmath=_FAST)
def _rows(yr, q, height):  # pragma: no cover - compiled
    """The pixel rows quad q's polygon may reach (a row's margin each side)."""
    return max(0, math.ceil(yr[q, 0] - 1.0)), min(height - 1, math.floor(yr[q, 1] + 1.0)) + 1


@nb.njit(cache=True, inline="always", error_model="numpy", fastmath=_FAST)
def _cols(lo, hi, width):  # pragma: no cover - compiled
    """The pixel columns [x0, x1] within a pixel of the x extent [lo, hi]."""
    return max(0, math.ceil(lo - 1.0)), min(width - 1, math.floor(hi + 1.0))


@nb.njit(cache=True, inline="always", error_model="numpy", fastmath=_FAST)
def _coverage(edges, n, q, x, y, inv_ramp):  # pragma: no cover - compiled
    """Soft coverage of point (x, y) by quad q's polygon: 1 inside, 0 outside, a linear ramp across
    each edge (its width the sub-sample spacing); the ramps' deficits add, so a sliver's coverage
    falls to 0 with its width."""
    deficit = 0.0
    for i in range(n):
        c = 0.5 + (edges[q, i, 0] * x + edges[q, i, 1] * y + edges[q, i, 2]) * inv_ramp
        if c < 1.0:
            deficit += 1.0 - c if c > 0.0 else 1.0
            if deficit >= 1.0:
                return 0.0
    return 1.0 - deficit


@nb.njit(cache=True, error_model="numpy", fastmath=_FAST)
def _render(quads, data, table, levels, texel, rot, centre, fx, fy, cx, cy, width, height, up,
            horizon, zenith, sub_x, sub_y, mask, row_lo, row_hi, out, depth, ids):  # pragma: no cover
    """The three passes of the module docstring over the pixels in ``mask`` (row y's between row_lo[y]
    and row_hi[y]); returns the number of anti-aliased pixels."""
    nq = quads.shape[0]
    cam = np.zeros((nq, 17))
    poly = np.zeros((nq, 8, 2))
    edges = np.zeros((nq, 8, 3))
    npoly = np.zeros(nq, np.int64)
    yr = np.zeros((nq, 2))
    _setup(quads, rot, centre, fx, fy, cx, cy, width, height, cam, poly, npoly, yr, edges)
    flag = np.zeros((height, width), np.uint8)
    out[:] = 0.0
    depth[:] = np.inf
    ids[:] = -1
    # 1. visibility at the pixel centres
    for q in range(nq):
        n = npoly[q]
        if n == 0:
            continue
        big_n, nx, ny, nz = cam[q, 12], cam[q, 9], cam[q, 10], cam[q, 11]
        ox, oy, oz = cam[q, 0], cam[q, 1], cam[q, 2]
        ax, ay, az, bx, by, bz = cam[q, 3], cam[q, 4], cam[q, 5], cam[q, 6], cam[q, 7], cam[q, 8]
        la, lb = cam[q, 13], cam[q, 14]
        sliver = yr[q, 1] - yr[q, 0] < THIN_PX
        for y in range(*_rows(yr, q, height)):
            if row_lo[y] > row_hi[y]:
                continue
            lo, hi = _span(poly, q, n, float(y), 1.0)
            x0, x1 = _cols(lo, hi, width)
            x0, x1 = max(x0, row_lo[y]), min(x1, row_hi[y])
            if lo > hi or x0 > x1:
                continue
            if sliver or hi - lo < THIN_PX:
                flag[y, x0:x1 + 1] = 1
            ry = (y - cy) / fy
            for x in range(x0, x1 + 1):
                if not mask[y, x]:
                    continue
                rx = (x - cx) / fx
                den = rx * nx + ry * ny + nz
                if den > -1e-12:
                    continue
                lam = big_n / den
                if lam >= depth[y, x]:
                    continue
                dx, dy, dz = lam * rx - ox, lam * ry - oy, lam - oz
                s = dx * ax + dy * ay + dz * az
                if s < 0.0 or s > la:
                    continue
                t = dx * bx + dy * by + dz * bz
                if t < 0.0 or t > lb:
                    continue
                depth[y, x] = lam
                ids[y, x] = q
    # shading at the centres; which pixels need sub-samples
    for y in range(height):
        for x in range(row_lo[y], row_hi[y] + 1):
            if not mask[y, x]:
                continue
            q = ids[y, x]
            if q < 0:
                out[y, x] = _sky(x, y, up, fx, fy, cx, cy, horizon, zenith)
            else:
                lum, near = _shade(cam, quads, data, table, levels, texel, q, x, y, fx, fy, cx, cy)
                out[y, x] = lum
                if near:
                    flag[y, x] = 1
            # each neighbour pair once (right, and the three below): both pixels of a differing pair
            for dy, dx in ((0, 1), (1, -1), (1, 0), (1, 1)):
                yy, xx = y + dy, x + dx
                if yy < height and 0 <= xx < width and ids[yy, xx] != q:
                    flag[y, x] = 1
                    flag[yy, xx] = 1
    slot = np.full((height, width), -1, np.int64)
    count = 0
    for y in range(height):
        for x in range(row_lo[y], row_hi[y] + 1):
            if flag[y, x] and mask[y, x]:
                slot[y, x] = count
                count += 1
    # 2. the quads that may reach each flagged pixel, with their depth at its centre (the nearest MAXC)
    cand = np.empty((count, MAXC), np.int64)
    cand_z = np.empty((count, MAXC))
    ncand = np.zeros(count, np.int64)
    for q in range(nq):
        n = npoly[q]
        if n == 0:
            continue
        big_n, nx, ny, nz = cam[q, 12], cam[q, 9], cam[q, 10], cam[q, 11]
        for y in range(*_rows(yr, q, height)):
            if row_lo[y] > row_hi[y]:
                continue
            lo, hi = _span(poly, q, n, float(y), 1.0)
            x0, x1 = _cols(lo, hi, width)
            x0, x1 = max(x0, row_lo[y]), min(x1, row_hi[y])
            if lo > hi or x0 > x1:
                continue
            ry = (y - cy) / fy
            for x in range(x0, x1 + 1):
                k = slot[y, x]
                if k < 0:
                    continue
                reach = np.inf  # the signed distance from the centre to the polygon (min over its edges)
                for i in range(n):
                    reach = min(reach, edges[q, i, 0] * x + edges[q, i, 1] * y + edges[q, i, 2])
                if reach < -_SUB_REACH:  # no sub-sample's ramp reaches it
                    continue
                den = (x - cx) / fx * nx + ry * ny + nz
                z = big_n / den if den < -1e-12 else np.inf
                m = ncand[k]
                if m < MAXC:
                    cand[k, m], cand_z[k, m] = q, z
                    ncand[k] = m + 1
                else:  # full: this one replaces the farthest, if nearer
                    far = 0
                    for j in range(1, MAXC):
                        if cand_z[k, j] > cand_z[k, far]:
                            far = j
                    if z < cand_z[k, far]:
                        cand[k, far], cand_z[k, far] = q, z
    # 3. each flagged pixel: at each sub-sample, the quads covering it composited front to back (by their
    # depths there: a contact line flips their order at one sub-sample at a time), with soft coverage
    ns = len(sub_x)
    inv_ramp = math.sqrt(ns)
    weight = np.empty(MAXC)
    mx = np.empty(MAXC)
    my = np.empty(MAXC)
    hit = np.empty(MAXC, np.int64)
    hit_c = np.empty(MAXC)
    hit_z = np.empty(MAXC)
    for y in range(height):
        for x in range(row_lo[y], row_hi[y] + 1):
            k = slot[y, x]
            if k < 0:
                continue
            m = ncand[k]
            for j in range(m):
                weight[j], mx[j], my[j] = 0.0, 0.0, 0.0
            sky = 0.0
            for s in range(ns):
                px, py = x + sub_x[s], y + sub_y[s]
                rx, ry = (px - cx) / fx, (py - cy) / fy
                h = 0
                for j in range(m):
                    q = cand[k, j]
                    c = _coverage(edges, npoly[q], q, px, py, inv_ramp)
                    if c <= 0.0:
                        continue
                    den = rx * cam[q, 9] + ry * cam[q, 10] + cam[q, 11]
                    z = cam[q, 12] / den if den < -1e-12 else np.inf
                    i = h  # insertion by depth
                    while i > 0 and hit_z[i - 1] > z:
                        hit[i], hit_c[i], hit_z[i] = hit[i - 1], hit_c[i - 1], hit_z[i - 1]
                        i -= 1
                    hit[i], hit_c[i], hit_z[i] = j, c, z
                    h += 1
                left = 1.0  # coverages taken as disjoint shares of the sub-sample's area, nearest first:
                for i in range(h):  # two faces meeting at an edge share it, and nothing behind shows
                    j = hit[i]
                    w = min(hit_c[i], left)
                    weight[j] += w
                    mx[j] += w * sub_x[s]
                    my[j] += w * sub_y[s]
                    left -= w
                    if left <= 1e-12:
                        break
                sky += max(left, 0.0)
            centre_q = ids[y, x]
            total = sky * (out[y, x] if centre_q < 0 else _sky(x, y, up, fx, fy, cx, cy, horizon, zenith))
            for j in range(m):
                if weight[j] <= 0.0:
                    continue
                q = cand[k, j]
                if q == centre_q:
                    lum = out[y, x]
                else:
                    lum = _shade(cam, quads, data, table, levels, texel, q, x + mx[j] / weight[j],
                                 y + my[j] / weight[j], fx, fy, cx, cy)[0]
                total += weight[j] * lum
            out[y, x] = total / ns
    return count


# --------------------------------------------------------------------------------------------- frames

@dataclass(frozen=True)
class Sky:
    """The background where no quad is hit: ``horizon`` luminance at elevation 0 (and below), easing
    towards ``zenith`` upwards; ``up`` is the world's up direction."""

    horizon: float = 0.75
    zenith: float = 0.55
    up: tuple[float, float, float] = (0.0, 0.0, 1.0)


@dataclass(frozen=True)
class Frame:
    """A rendered frame: ``luminance`` float64 [H, W] (the anti-aliased image), the centre samples'
    ``depth`` (camera z, metres; inf for the sky) and ``quad`` (index, -1 for the sky), and how many
    pixels were anti-aliased."""

    luminance: np.ndarray
    depth: np.ndarray
    quad: np.ndarray
    antialiased: int


def check_quads(quads: np.ndarray, textures: Textures) -> np.ndarray:
    """``quads`` as a contiguous float64 [Q, QUAD_FIELDS] whose texture ids exist; InvalidInputError else."""
    quads = np.ascontiguousarray(quads, dtype=np.float64)
    if quads.ndim != 2 or quads.shape[1] != QUAD_FIELDS:
        raise InvalidInputError(f"quads must be [Q, {QUAD_FIELDS}], got shape {quads.shape}")
    if not np.isfinite(quads).all():
        raise InvalidInputError("quads hold NaN or Inf")
    tex = quads[:, 9]
    if len(tex) and (tex.min() < 0 or tex.max() >= len(textures) or np.any(tex != np.round(tex))):
        raise InvalidInputError(f"quad texture ids must be integers in 0..{len(textures) - 1}")
    return quads


def render(quads: np.ndarray, textures: Textures, c2w: np.ndarray, intrinsics: Intrinsics,
           sky: Sky = Sky(), mask: np.ndarray | None = None) -> Frame:
    """The frame seen from camera-to-world ``c2w`` (OpenCV axes) with ``intrinsics``; with ``mask`` (bool
    [H, W]) only its pixels (the others 0, depth inf, quad -1), each as in the whole frame."""
    quads = check_quads(quads, textures)
    c2w = validate_pose(c2w, name="c2w")
    if not isinstance(intrinsics, Intrinsics):
        raise InvalidInputError(f"intrinsics must be an Intrinsics, got {type(intrinsics).__name__}")
    k = intrinsics
    h, w = k.height, k.width
    out = np.empty((h, w))
    depth = np.empty((h, w))
    ids = np.empty((h, w), np.int64)
    if mask is None:
        mask = np.ones((h, w), np.uint8)
    else:
        mask = np.asarray(mask)
        if mask.shape != (h, w):
            raise InvalidInputError(f"mask must be [{h}, {w}] like the image, got shape {mask.shape}")
        mask = np.ascontiguousarray(mask, dtype=np.uint8)
    rows = mask.any(axis=1)
    row_lo = np.where(rows, mask.argmax(axis=1), w).astype(np.int64)
    row_hi = np.where(rows, w - 1 - mask[:, ::-1].argmax(axis=1), -1).astype(np.int64)
    rot = np.ascontiguousarray(c2w[:3, :3].T)
    up = rot @ np.asarray(sky.up, np.float64)
    count = _render(quads, textures.data, textures.table, textures.levels, textures.texel_m, rot,
                    np.ascontiguousarray(c2w[:3, 3]), float(k.fx), float(k.fy), float(k.cx), float(k.cy),
                    w, h, up, float(sky.horizon), float(sky.zenith), _SUB_X, _SUB_Y, mask, row_lo, row_hi,
                    out, depth, ids)
    return Frame(out, depth, ids, int(count))
