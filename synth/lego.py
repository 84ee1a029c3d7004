"""``lego``: a rigid mechanism with moving parts (rigid mechanical motion).

On a studded base plate: a pinwheel-painted flywheel turning at an uneven speed drives a piston
through a connecting rod (crank-slider kinematics, solved exactly at every t); a crane boom on a
tower swings back and forth; a small turntable spins. Each part moves rigidly; together the
speeds (wheel ~2 rev/s with an 8-sector pattern, so it aliases at 5 and 10 fps) defeat any smooth
interpolation between anchors.
"""

from __future__ import annotations

import numpy as np

from edmcgs.geometry import rotmat_to_quat
from edmcgs.synth.cloud import Cloud, pose_parts, rotation
from edmcgs.synth.orbit import Orbit
from edmcgs.synth.primitives import box, checker, cylinder, sectors, solid, stripes
from edmcgs.synth.scene import ProceduralScene, Size

DURATION_S = 2.0
SPACING_M = 0.022
RED, YELLOW, BLUE = (0.85, 0.1, 0.08), (0.98, 0.8, 0.1), (0.08, 0.3, 0.8)
WHITE, GREY, DARK = (0.95, 0.95, 0.95), (0.6, 0.62, 0.65), (0.12, 0.12, 0.14)

WHEEL_CENTER = np.array([0.1, -0.12, 0.42])
CRANK = 0.19  # crank pin radius on the wheel
ROD = 0.5  # connecting rod length, pin to pin
BOOM_PIVOT = np.array([-0.5, 0.0, 0.86])
TURNTABLE_CENTER = np.array([0.55, 0.12, 0.13])
PARTS = ("base", "wheel", "rod", "piston", "boom", "turntable")


def wheel_angle(t: float) -> float:
    """Flywheel angle: ~2 rev/s, sped up and slowed down once every 0.8 s."""
    return 2 * np.pi * t / 0.5 + 0.8 * np.sin(2 * np.pi * t / 0.8)


def _parts(spacing: float) -> list[Cloud]:
    """Each part in its own frame (see ``Lego.at`` for where the frames go)."""
    base = Cloud.concat([
        box((0, 0, 0.05), (1.5, 0.6, 0.1), spacing, checker(0.2, GREY, YELLOW)),
        box((-0.5, 0, 0.45), (0.16, 0.16, 0.7), spacing, stripes(2, 0.14, RED, WHITE)),  # the tower
        box((0.62, -0.12, 0.42), (0.5, 0.04, 0.14), spacing, solid(DARK)),  # the piston's guide
    ])
    wheel = Cloud.concat([  # axis along local z; the crank pin sticks out towards +z
        cylinder(0.28, 0.06, spacing, sectors(8, RED, WHITE)),
        cylinder(0.035, 0.08, spacing, solid(DARK)).translated((CRANK, 0, 0.06)),
    ])
    rod = box((0.5 * ROD, 0, 0), (ROD + 0.06, 0.04, 0.05), spacing, stripes(0, 0.1, BLUE, WHITE))
    piston = box((0.12, 0, 0), (0.24, 0.1, 0.11), spacing, stripes(0, 0.08, YELLOW, DARK))
    boom = Cloud.concat([box((0.3, 0, 0), (0.8, 0.08, 0.08), spacing, stripes(0, 0.1, YELLOW, DARK)),
                         box((0.68, 0, -0.1), (0.06, 0.06, 0.2), spacing, solid(BLUE))])
    turntable = cylinder(0.13, 0.05, spacing, sectors(6, BLUE, YELLOW))
    return [base, wheel, rod, piston, boom, turntable]


class Lego:
    def __init__(self, spacing: float) -> None:
        parts = _parts(spacing)
        self.rest = Cloud.concat(parts)
        self.part = np.concatenate([np.full(len(c), i) for i, c in enumerate(parts)])

    def transforms(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """World rotation [P, 3, 3] and translation [P, 3] of each part at t."""
        face_front = rotation("x", np.pi / 2)  # local z -> world -y (towards the camera)
        wheel_rot = rotation("y", -wheel_angle(t)) @ face_front
        pin = WHEEL_CENTER + wheel_rot @ np.array([CRANK, 0.0, 0.06])
        # crank-slider: the piston pin stays at the wheel centre's height, ROD away from the crank pin
        dz = WHEEL_CENTER[2] - pin[2]
        slider = np.array([pin[0] + np.sqrt(ROD**2 - dz**2), pin[1], WHEEL_CENTER[2]])
        d = (slider - pin) / ROD
        rod_rot = rotation("y", np.arctan2(-d[2], d[0]))
        boom = 0.7 * np.sin(2 * np.pi * t / 0.9) + 0.25 * np.sin(2 * np.pi * t / 0.37)
        rots = [np.eye(3), wheel_rot, rod_rot, np.eye(3), rotation("z", boom),
                rotation("z", 2 * np.pi * t / 0.3)]
        trans = [np.zeros(3), WHEEL_CENTER, pin - [0, 0.03, 0], slider, BOOM_PIVOT, TURNTABLE_CENTER]
        return np.stack(rots), np.stack(trans)

    def at(self, t: float) -> Cloud:
        rot, trans = self.transforms(t)
        return pose_parts(self.rest, self.part, rot, rotmat_to_quat(rot), trans)


def make(size: Size) -> ProceduralScene:
    mechanism = Lego(SPACING_M * size.spacing_scale)
    orbit = Orbit(target=(0.05, 0.0, 0.42), radius=2.1, elevation_deg=18.0,
                  azimuth_start_deg=-20.0, azimuth_end_deg=15.0, duration_s=DURATION_S)
    return ProceduralScene(name="lego", intrinsics=size.intrinsics, duration_s=DURATION_S,
                           orbit=orbit, motion=mechanism.at)
