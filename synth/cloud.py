"""A set of 3D Gaussians as plain numpy arrays, and the rigid motions the procedural scenes apply to it."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from edmcgs.geometry import quat_multiply


@dataclass(frozen=True, eq=False)
class Cloud:
    """Gaussians in the rasterizer's parametrisation (float64 while a scene is built and posed).

    means: [N, 3]; quats: [N, 4] unit (w, x, y, z); scales: [N, 3] linear standard deviations (> 0);
    opacities: [N] in (0, 1]; colors: [N, 3] linear RGB in [0, 1].
    """

    means: np.ndarray
    quats: np.ndarray
    scales: np.ndarray
    opacities: np.ndarray
    colors: np.ndarray

    def __len__(self) -> int:
        return len(self.means)

    def replace(self, **changes) -> Cloud:
        """A copy with some arrays swapped (the others shared)."""
        fields = {k: getattr(self, k) for k in ("means", "quats", "scales", "opacities", "colors")}
        return Cloud(**(fields | changes))

    def translated(self, offset) -> Cloud:
        return self.replace(means=self.means + np.asarray(offset, dtype=np.float64))

    def as_float32(self) -> Cloud:
        return Cloud(*(np.ascontiguousarray(a, dtype=np.float32)
                       for a in (self.means, self.quats, self.scales, self.opacities, self.colors)))

    @staticmethod
    def concat(clouds: list[Cloud]) -> Cloud:
        return Cloud(*(np.concatenate([getattr(c, k) for c in clouds])
                       for k in ("means", "quats", "scales", "opacities", "colors")))


def axis_angle_quat(axis, angle) -> np.ndarray:
    """Quaternion [..., 4] of a rotation by ``angle`` (radians, array-like) about a fixed unit ``axis``."""
    angle = np.asarray(angle, dtype=np.float64)
    axis = np.asarray(axis, dtype=np.float64)
    half = 0.5 * angle[..., None]
    return np.concatenate([np.cos(half), np.sin(half) * axis], axis=-1)


def rotation(axis: str, angle: float) -> np.ndarray:
    """3x3 rotation by ``angle`` radians about the world axis "x", "y" or "z"."""
    c, s = np.cos(angle), np.sin(angle)
    if axis == "x":
        return np.array([[1.0, 0, 0], [0, c, -s], [0, s, c]])
    if axis == "y":
        return np.array([[c, 0, s], [0, 1.0, 0], [-s, 0, c]])
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])


def pose_parts(cloud: Cloud, part: np.ndarray, rot: np.ndarray, rot_q: np.ndarray,
               trans: np.ndarray) -> Cloud:
    """Move each Gaussian rigidly with its part.

    cloud: the Gaussians in their parts' local frames; part: int [N] part index of each Gaussian;
    rot: [P, 3, 3] and rot_q: [P, 4] (the same rotations as quaternions); trans: [P, 3].
    Means go to R p + T, orientations to q_R * q.
    """
    means = np.einsum("nij,nj->ni", rot[part], cloud.means) + trans[part]
    quats = quat_multiply(rot_q[part], cloud.quats)
    return cloud.replace(means=means, quats=quats)
