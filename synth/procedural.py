"""Procedural 2D texture tools: lattice hashes, value noise, fbm and anti-aliased shape coverage.

Every function is deterministic (a key or seed selects the pattern) and vectorised over numpy arrays of
coordinates; the shapes are signed distances turned into a coverage ramp one output pixel wide, so a
texture drawn with them is band-limited at the scale it is drawn for (``synth.traffic``'s street,
``synth.street3d``'s textures).
"""

from __future__ import annotations

import numpy as np

from edmcgs.errors import InvalidInputError


def _mix64(h: np.ndarray) -> np.ndarray:
    """splitmix64 finaliser on uint64 arrays."""
    h = h ^ (h >> np.uint64(30))
    h = h * np.uint64(0xBF58476D1CE4E5B9)
    h = h ^ (h >> np.uint64(27))
    h = h * np.uint64(0x94D049BB133111EB)
    return h ^ (h >> np.uint64(31))


def hash01(ix: np.ndarray, iy: np.ndarray, key: int) -> np.ndarray:
    """A deterministic value in [0, 1) per integer lattice point (any sign) and key: float64."""
    with np.errstate(over="ignore"):
        h = (np.asarray(ix, np.int64).astype(np.uint64) * np.uint64(0x9E3779B97F4A7C15)
             + np.asarray(iy, np.int64).astype(np.uint64) * np.uint64(0xC2B2AE3D27D4EB4F)
             + np.uint64(key & 0xFFFFFFFFFFFFFFFF))
        h = _mix64(h)
    return (h >> np.uint64(11)).astype(np.float64) * (1.0 / (1 << 53))


_TABLE_BITS = 10
_TABLE: list[np.ndarray] = []


def _lattice() -> np.ndarray:
    """A 1024x1024 table of lattice values in [0, 1), flattened (built once, shared by every key)."""
    if not _TABLE:
        n = 1 << _TABLE_BITS
        _TABLE.append(hash01(np.arange(n)[None, :], np.arange(n)[:, None], 0x5EED).ravel())
    return _TABLE[0]


def value_noise(u: np.ndarray, v: np.ndarray, spacing: float, key: int,
                period: float | None = None) -> np.ndarray:
    """Smooth value noise in [-1, 1] with lattice ``spacing`` (in u, v units): continuous, C1 across cells.

    The lattice values come from one shared table (period 1024 cells), read at an offset per ``key``.
    period: repeat every ``period`` in u and v (a whole number of cells, a power of two up to 1024), so
    that a texture drawn with it tiles without seams.
    """
    x, y = u / spacing, v / spacing
    ix, iy = np.floor(x), np.floor(y)
    fx, fy = x - ix, y - iy
    wx, wy = fx * fx * (3 - 2 * fx), fy * fy * (3 - 2 * fy)
    mask = (1 << _TABLE_BITS) - 1
    cells = mask
    if period is not None:
        n = round(period / spacing)
        if n < 1 or n > mask + 1 or n & (n - 1) or abs(n * spacing - period) > 1e-9 * period:
            raise InvalidInputError(f"period {period} is not a power of two (<= 1024) of {spacing} cells")
        cells = n - 1
    offset = hash01(np.array([key, key + 1]), np.array([1, 2]), 0x0FF5E7)
    ix, iy = ix.astype(np.int64), iy.astype(np.int64)
    ix0, iy0 = int(offset[0] * 1024), int(offset[1] * 1024)
    ix1, iy1 = ((((ix + 1) & cells) + ix0) & mask), (((((iy + 1) & cells) + iy0) & mask) << _TABLE_BITS)
    ix = ((ix & cells) + ix0) & mask
    iy = (((iy & cells) + iy0) & mask) << _TABLE_BITS
    table = _lattice()
    a, b, c, d = table[iy + ix], table[iy + ix1], table[iy1 + ix], table[iy1 + ix1]
    return 2.0 * ((a + (b - a) * wx) * (1 - wy) + (c + (d - c) * wx) * wy) - 1.0


def fbm(u, v, spacings, key: int, px: float, period: float | None = None) -> np.ndarray:
    """Sum of value-noise octaves (amplitude ~ spacing^0.6, normalised to about [-1, 1]); octaves with
    a lattice finer than two output pixels (``px`` u, v units each) are left out (no aliasing).
    period: see ``value_noise``."""
    out = np.zeros(np.broadcast_shapes(np.shape(u), np.shape(v)))
    total = 0.0
    for i, s in enumerate(spacings):
        amp = s ** 0.6
        total += amp
        if s >= 2.0 * px:
            out += amp * value_noise(u, v, s, key * 131 + i, period)
    return out / total


def ramp(sd: np.ndarray, px: float) -> np.ndarray:
    """Coverage of a signed distance (negative inside) over a ramp one output pixel (``px``) wide."""
    return np.clip(0.5 - sd / px, 0.0, 1.0)


def box_sd(a, b, half_a, half_b, radius=0.0):
    """Signed distance to a rounded box centred at 0 (half sizes include the rounding)."""
    qa = np.abs(a) - half_a + radius
    qb = np.abs(b) - half_b + radius
    outside = np.hypot(np.maximum(qa, 0.0), np.maximum(qb, 0.0))
    return outside + np.minimum(np.maximum(qa, qb), 0.0) - radius


def band(v, lo, hi, px):
    """Coverage of lo <= v < hi."""
    return ramp(np.abs(v - 0.5 * (lo + hi)) - 0.5 * (hi - lo), px)
