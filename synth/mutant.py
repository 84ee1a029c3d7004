"""``mutant``: a blobby creature whose body deforms non-rigidly (no part of it moves rigidly).

Rest shape: a trunk, a head and four tentacles. At time t a smooth deformation field moves every
Gaussian: the tentacles curl about their roots by an angle growing along their length, then the
whole body bulges in travelling rings, twists about its axis and sways in a bending wave. Each
Gaussian's orientation follows the field's local rotation and its in-surface size the bulge. The
periods (0.36 to 0.62 s) are incommensurate, so no two anchors look alike.
"""

from __future__ import annotations

import numpy as np

from edmcgs.geometry import quat_multiply, rotmat_to_quat
from edmcgs.synth.cloud import Cloud, axis_angle_quat, rotation
from edmcgs.synth.orbit import Orbit
from edmcgs.synth.primitives import capsule, ellipsoid, stripes
from edmcgs.synth.scene import ProceduralScene, Size

DURATION_S = 2.0
SPACING_M = 0.022
TENTACLES = 4
TENTACLE_LENGTH = 0.6
TENTACLE_ROOT_Z = 0.95
BODY_BASE_Z, BODY_HEIGHT = 0.1, 1.5


def _tentacle_root(i: int) -> np.ndarray:
    yaw = np.pi / 4 + i * np.pi / 2
    return np.array([0.25 * np.cos(yaw), 0.22 * np.sin(yaw), TENTACLE_ROOT_Z])


def _rest(spacing: float) -> tuple[Cloud, np.ndarray]:
    """Rest Gaussians (world frame) and the tentacle of each (-1 for the body)."""
    trunk = ellipsoid((0, 0, 0.75), (0.34, 0.3, 0.62), spacing,
                      stripes(2, 0.16, (0.45, 0.15, 0.6), (0.55, 0.85, 0.3)))
    head = ellipsoid((0, -0.03, 1.45), (0.24, 0.22, 0.2), spacing,
                     stripes(0, 0.12, (0.9, 0.75, 0.2), (0.35, 0.1, 0.45)))
    parts, labels = [trunk, head], [np.full(len(trunk), -1), np.full(len(head), -1)]
    for i in range(TENTACLES):
        yaw = np.pi / 4 + i * np.pi / 2
        tentacle = capsule(TENTACLE_LENGTH, 0.065, spacing,
                           stripes(2, 0.12, (0.95, 0.45, 0.35), (0.25, 0.2, 0.55)))
        # the capsule hangs along -z from its root: turn it out (slightly upwards), then about the body
        rot = rotation("z", yaw + np.pi) @ rotation("y", np.pi / 2 + 0.25)
        parts.append(tentacle.replace(means=tentacle.means @ rot.T + _tentacle_root(i),
                                      quats=quat_multiply(rotmat_to_quat(rot), tentacle.quats)))
        labels.append(np.full(len(tentacle), i))
    return Cloud.concat(parts), np.concatenate(labels)


def _rotations(axis: np.ndarray, angle: np.ndarray) -> np.ndarray:
    """Rotation matrices [N, 3, 3] by ``angle`` [N] about unit ``axis`` ([3] or [N, 3]) (Rodrigues)."""
    axis = np.broadcast_to(axis, (len(angle), 3))
    k = np.zeros((len(angle), 3, 3))
    k[:, 0, 1], k[:, 0, 2], k[:, 1, 2] = -axis[:, 2], axis[:, 1], -axis[:, 0]
    k -= np.swapaxes(k, 1, 2)
    s, c = np.sin(angle)[:, None, None], np.cos(angle)[:, None, None]
    return np.eye(3) + s * k + (1 - c) * (k @ k)


class Mutant:
    def __init__(self, spacing: float) -> None:
        self.rest, self.tentacle = _rest(spacing)

    def at(self, t: float) -> Cloud:
        means = self.rest.means.copy()
        quats = self.rest.quats.copy()
        scales = self.rest.scales.copy()
        # 1. tentacles curl about the horizontal axis across them, more towards their tips
        for i in range(TENTACLES):
            sel = self.tentacle == i
            yaw = np.pi / 4 + i * np.pi / 2
            root = _tentacle_root(i)
            rel = means[sel] - root
            reach = np.clip(np.hypot(rel[:, 0], rel[:, 1]) / TENTACLE_LENGTH, 0.0, 1.2)
            angle = 1.1 * np.sin(2 * np.pi * t / 0.42 + 1.7 * i) * reach ** 1.5
            axis = np.array([-np.sin(yaw), np.cos(yaw), 0.0])
            means[sel] = root + np.einsum("nij,nj->ni", _rotations(axis, angle), rel)
            quats[sel] = quat_multiply(axis_angle_quat(axis, angle), quats[sel])
        # 2. the body field: bulging rings, twist, bending sway
        z = self.rest.means[:, 2]
        h = np.clip((z - BODY_BASE_Z) / BODY_HEIGHT, 0.0, 1.0)
        bulge = 1.0 + 0.15 * np.sin(2 * np.pi * t / 0.36 - 5.0 * z)
        twist = 0.6 * np.sin(2 * np.pi * t / 0.62) * h
        sx = 0.2 * np.sin(2 * np.pi * t / 0.45 - 2.0 * z)
        sy = 0.13 * np.sin(2 * np.pi * t / 0.53 + 1.3 - 2.0 * z)
        c, s = np.cos(twist), np.sin(twist)
        x, y = bulge * means[:, 0], bulge * means[:, 1]
        means[:, 0], means[:, 1] = c * x - s * y + sx * h * h, s * x + c * y + sy * h * h
        # the sway's slope tilts the surface: d(offset)/dz
        dh = (h < 1) / BODY_HEIGHT
        dsx = -0.4 * np.cos(2 * np.pi * t / 0.45 - 2.0 * z) * h * h + sx * 2 * h * dh
        dsy = -0.26 * np.cos(2 * np.pi * t / 0.53 + 1.3 - 2.0 * z) * h * h + sy * 2 * h * dh
        tilt = quat_multiply(axis_angle_quat([0, 1.0, 0], np.arctan(dsx)),
                             axis_angle_quat([1.0, 0, 0], -np.arctan(dsy)))
        quats = quat_multiply(quat_multiply(tilt, axis_angle_quat([0, 0, 1.0], twist)), quats)
        scales[:, :2] *= bulge[:, None]
        return self.rest.replace(means=means, quats=quats, scales=scales)


def make(size: Size) -> ProceduralScene:
    creature = Mutant(SPACING_M * size.spacing_scale)
    orbit = Orbit(target=(0.0, 0.0, 0.8), radius=2.5, elevation_deg=15.0,
                  azimuth_start_deg=20.0, azimuth_end_deg=-20.0, duration_s=DURATION_S)
    return ProceduralScene(name="mutant", intrinsics=size.intrinsics, duration_s=DURATION_S,
                           orbit=orbit, motion=creature.at)
