"""The synthetic camera: DAVIS346 intrinsics and a slow, continuous arc around the object."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from edmcgs.errors import InvalidInputError
from edmcgs.geometry import Intrinsics

DAVIS346 = Intrinsics(fx=300.0, fy=300.0, cx=172.5, cy=129.5, width=346, height=260)
"""346x260 with a 60 degree horizontal field of view, principal point at the centre."""


def look_at(eye, target, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """Camera-to-world float64 [4, 4], OpenCV convention (x right, y down, z towards ``target``)."""
    eye, target, up = (np.asarray(v, dtype=np.float64) for v in (eye, target, up))
    z = target - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    norm = np.linalg.norm(x)
    if norm < 1e-9:
        raise InvalidInputError("look_at: the viewing direction is parallel to the up vector")
    x /= norm
    c2w = np.eye(4)
    c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = x, np.cross(z, x), z, eye
    return c2w


@dataclass(frozen=True)
class Orbit:
    """A camera circling ``target`` at a fixed distance and elevation, its azimuth moving at constant
    speed from ``azimuth_start_deg`` (at t = 0) to ``azimuth_end_deg`` (at t = ``duration_s``).

    Azimuth 0 puts the camera on the -y side of the target (facing the figures' front), positive
    azimuths towards +x. Outside [0, duration_s] the arc extends analytically (circling on), or with
    ``sweep`` goes back and forth over the same arc (a pan that keeps to the views of [0, duration_s]).
    """

    target: tuple[float, float, float]
    radius: float
    elevation_deg: float
    azimuth_start_deg: float
    azimuth_end_deg: float
    duration_s: float
    sweep: bool = False

    def c2w(self, t_s: float) -> np.ndarray:
        """Camera-to-world float64 [4, 4] at scene time ``t_s`` (seconds)."""
        if not math.isfinite(t_s):
            raise InvalidInputError(f"t_s must be finite, got {t_s!r}")
        along = t_s / self.duration_s  # fraction of the arc
        if self.sweep:
            along = 1.0 - abs(along % 2.0 - 1.0)  # 0 -> 1 over [0, duration_s], then back, and so on
        az = math.radians(self.azimuth_start_deg + (self.azimuth_end_deg - self.azimuth_start_deg) * along)
        el = math.radians(self.elevation_deg)
        direction = np.array([math.sin(az) * math.cos(el), -math.cos(az) * math.cos(el), math.sin(el)])
        target = np.asarray(self.target, dtype=np.float64)
        return look_at(target + self.radius * direction, target)
