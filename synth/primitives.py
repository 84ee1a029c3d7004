"""Surfaces covered with flat Gaussians, and the textures that colour them.

Every shape is sampled on its surface at about ``spacing`` metres between neighbours (deterministic:
Fibonacci spirals and staggered grids, no randomness), each sample a Gaussian flattened along the
surface normal, so the shapes render as opaque, smoothly shaded solids. Colour is a function of the
sample's position in the shape's frame (a texture), fixed at build time: the scenes move geometry only.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from edmcgs.geometry import rotmat_to_quat
from edmcgs.synth.cloud import Cloud

Texture = Callable[[np.ndarray], np.ndarray]
"""points [N, 3] in the shape's frame -> colours [N, 3] in [0, 1]."""

TANGENT_SIGMA = 0.6
"""Gaussian standard deviation along the surface, in units of the spacing: neighbours overlap."""
NORMAL_SIGMA = 0.15
"""Standard deviation across the surface, in units of the spacing: thin, so silhouettes stay sharp."""
OPACITY = 0.9

_GOLDEN = np.pi * (3.0 - np.sqrt(5.0))


# ------------------------------------------------------------------------------------------ textures

def solid(color) -> Texture:
    c = np.asarray(color, dtype=np.float64)
    return lambda p: np.broadcast_to(c, (len(p), 3)).copy()


def stripes(axis: int, period: float, a, b, offset: float = 0.0) -> Texture:
    """Bands of colours a and b, each half a ``period`` long, along coordinate ``axis``."""
    a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    return lambda p: np.where((np.floor((p[:, axis] + offset) / (0.5 * period)) % 2 == 0)[:, None], a, b)


def checker(period: float, a, b) -> Texture:
    """A 3D checkerboard of cells ``period / 2`` wide."""
    a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    return lambda p: np.where((np.floor(p / (0.5 * period)).sum(axis=1) % 2 == 0)[:, None], a, b)


def sectors(n: int, a, b, axis: int = 2) -> Texture:
    """``n`` angular sectors around ``axis`` alternating a and b (n even), like a pinwheel."""
    a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    u, v = [(axis + 1) % 3, (axis + 2) % 3]

    def paint(p):
        k = np.floor((np.arctan2(p[:, v], p[:, u]) + np.pi) / (2 * np.pi / n)).astype(int)
        return np.where((k % 2 == 0)[:, None], a, b)
    return paint


# -------------------------------------------------------------------------------------------- shapes

def _splats(points: np.ndarray, normals: np.ndarray, spacing: float, texture: Texture) -> Cloud:
    """Flat Gaussians at ``points`` facing ``normals`` (unit, [N, 3])."""
    helper = np.where(np.abs(normals[:, 2:3]) < 0.9, [[0.0, 0.0, 1.0]], [[1.0, 0.0, 0.0]])
    t1 = np.cross(helper, normals)
    t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
    t2 = np.cross(normals, t1)
    frames = np.stack([t1, t2, normals], axis=2)  # columns: local x, y, z -> world
    n = len(points)
    scales = np.tile([TANGENT_SIGMA * spacing, TANGENT_SIGMA * spacing, NORMAL_SIGMA * spacing], (n, 1))
    return Cloud(means=points, quats=rotmat_to_quat(frames), scales=scales, opacities=np.full(n, OPACITY),
                 colors=np.clip(texture(points), 0.0, 1.0))


def _fibonacci_sphere(n: int, z_min: float = -1.0) -> np.ndarray:
    """About-uniform unit vectors [n, 3] with z in [z_min, 1] (a whole sphere or a cap)."""
    i = np.arange(n) + 0.5
    z = 1.0 - (1.0 - z_min) * i / n
    r = np.sqrt(np.clip(1.0 - z * z, 0.0, None))
    phi = _GOLDEN * i
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


def ellipsoid(center, radii, spacing: float, texture: Texture) -> Cloud:
    """An ellipsoid with semi-axes ``radii`` (x, y, z) around ``center``."""
    center, radii = np.asarray(center, dtype=np.float64), np.asarray(radii, dtype=np.float64)
    a, b, c = radii
    p = 1.6075  # Knud Thomsen's approximation of the surface area (within ~1 %)
    area = 4 * np.pi * (((a * b) ** p + (a * c) ** p + (b * c) ** p) / 3) ** (1 / p)
    unit = _fibonacci_sphere(max(8, round(area / spacing**2)))
    normals = unit / radii
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    return _splats(center + unit * radii, normals, spacing, texture)


def capsule(length: float, radius: float, spacing: float, texture: Texture) -> Cloud:
    """A cylinder of ``radius`` from the origin down to z = -length, closed by hemispheres (a limb)."""
    n_around = max(6, round(2 * np.pi * radius / spacing))
    n_along = max(1, round(length / spacing))
    k = np.arange(n_around * n_along)
    ring, step = k // n_around, k % n_around
    phi = 2 * np.pi * (step + 0.5 * (ring % 2)) / n_around  # staggered rows
    z = -(ring + 0.5) * length / n_along
    side_n = np.stack([np.cos(phi), np.sin(phi), np.zeros_like(phi)], axis=1)
    side_p = side_n * radius + np.stack([0 * z, 0 * z, z], axis=1)
    cap = _fibonacci_sphere(max(4, round(2 * np.pi * radius**2 / spacing**2)), z_min=0.0)
    top_p, bottom_n = cap * radius, cap * [1.0, 1.0, -1.0]
    bottom_p = bottom_n * radius + [0.0, 0.0, -length]
    return _splats(np.concatenate([side_p, top_p, bottom_p]), np.concatenate([side_n, cap, bottom_n]),
                   spacing, texture)


def box(center, size, spacing: float, texture: Texture) -> Cloud:
    """An axis-aligned box of edge lengths ``size`` (x, y, z) around ``center``."""
    center, half = np.asarray(center, dtype=np.float64), 0.5 * np.asarray(size, dtype=np.float64)
    points, normals = [], []
    for axis in range(3):
        u, v = (axis + 1) % 3, (axis + 2) % 3
        nu, nv = max(1, round(2 * half[u] / spacing)), max(1, round(2 * half[v] / spacing))
        gu = (np.arange(nu) + 0.5) / nu * 2 * half[u] - half[u]
        gv = (np.arange(nv) + 0.5) / nv * 2 * half[v] - half[v]
        uu, vv = (g.ravel() for g in np.meshgrid(gu, gv, indexing="ij"))
        for sign in (-1.0, 1.0):
            p = np.zeros((len(uu), 3))
            p[:, axis], p[:, u], p[:, v] = sign * half[axis], uu, vv
            nrm = np.zeros_like(p)
            nrm[:, axis] = sign
            points.append(p)
            normals.append(nrm)
    return _splats(center + np.concatenate(points), np.concatenate(normals), spacing, texture)


def cylinder(radius: float, height: float, spacing: float, texture: Texture) -> Cloud:
    """A closed cylinder around the z axis from z = -height/2 to +height/2 (a wheel, a disc)."""
    n_around = max(8, round(2 * np.pi * radius / spacing))
    n_along = max(1, round(height / spacing))
    k = np.arange(n_around * n_along)
    ring, step = k // n_around, k % n_around
    phi = 2 * np.pi * (step + 0.5 * (ring % 2)) / n_around
    z = -0.5 * height + (ring + 0.5) * height / n_along
    side_n = np.stack([np.cos(phi), np.sin(phi), np.zeros_like(phi)], axis=1)
    side_p = side_n * radius + np.stack([0 * z, 0 * z, z], axis=1)
    # sunflower spiral: about uniform points on a disc
    n_disc = max(4, round(np.pi * radius**2 / spacing**2))
    i = np.arange(n_disc) + 0.5
    r, phi = radius * np.sqrt(i / n_disc), _GOLDEN * i
    disc = np.stack([r * np.cos(phi), r * np.sin(phi), np.zeros(n_disc)], axis=1)
    lift = np.array([0.0, 0.0, 0.5 * height])
    caps_p = np.concatenate([disc + lift, disc - lift])
    caps_n = np.concatenate([np.tile([0.0, 0, 1], (n_disc, 1)), np.tile([0.0, 0, -1], (n_disc, 1))])
    return _splats(np.concatenate([side_p, caps_p]), np.concatenate([side_n, caps_n]), spacing, texture)
