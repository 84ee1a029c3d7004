"""``jumpingjack``: a figure doing fast jumping jacks, filling the frame (articulated, full-frame motion).

One jack takes ``PERIOD_S`` = 0.28 s, close to the 0.2 s between anchors at 5 fps: successive
anchors catch the arms at unrelated phases (the anchor poses alias to a slow drift), so a smooth
interpolator in time cannot recover the in-between poses, while the events record every swing.
"""

from __future__ import annotations

import numpy as np

from edmcgs.synth.cloud import rotation
from edmcgs.synth.figure import ROOT_HEIGHT, Figure
from edmcgs.synth.orbit import Orbit
from edmcgs.synth.scene import ProceduralScene, Size

PERIOD_S = 0.28
DURATION_S = 2.0
SPACING_M = 0.02
"""Surface spacing at full size (about 6k Gaussians)."""
PALETTE = {
    "shirt_a": (0.85, 0.15, 0.12), "shirt_b": (0.95, 0.9, 0.8),
    "arm_a": (0.1, 0.25, 0.75), "arm_b": (0.95, 0.8, 0.2),
    "leg_a": (0.08, 0.4, 0.2), "leg_b": (0.7, 0.85, 0.6),
    "hair": (0.15, 0.08, 0.05),
}


def pose(t_s: float) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """Local bone rotations and the pelvis position at t_s."""
    phase = 2 * np.pi * t_s / PERIOD_S
    open_ = 0.5 * (1 - np.cos(phase))  # 0: arms down, feet together; 1: arms up, feet apart
    airborne = np.sin(phase) ** 2  # the hops between the two stances
    arm = np.radians(12 + 150 * open_)
    elbow = np.radians(8 + 22 * airborne)
    leg = np.radians(3 + 20 * open_)
    knee = np.radians(4 + 16 * airborne)
    local = {
        "upper_arm_l": rotation("y", -arm), "forearm_l": rotation("y", -elbow),
        "upper_arm_r": rotation("y", arm), "forearm_r": rotation("y", elbow),
        "thigh_l": rotation("y", -leg) @ rotation("x", -0.5 * knee), "shin_l": rotation("x", knee),
        "thigh_r": rotation("y", leg) @ rotation("x", -0.5 * knee), "shin_r": rotation("x", knee),
        "head": rotation("x", np.radians(6) * np.sin(phase)),
    }
    drop = 0.9 * (1 - np.cos(leg)) + 0.87 * (1 - np.cos(0.5 * knee))  # spread, bent legs lower the hips
    root = np.array([0.0, 0.0, ROOT_HEIGHT - drop + 0.1 * airborne])
    return local, root


def make(size: Size) -> ProceduralScene:
    figure = Figure(SPACING_M * size.spacing_scale, PALETTE)
    orbit = Orbit(target=(0.0, 0.0, 1.12), radius=2.85, elevation_deg=8.0,
                  azimuth_start_deg=-25.0, azimuth_end_deg=25.0, duration_s=DURATION_S)
    return ProceduralScene(name="jumpingjack", intrinsics=size.intrinsics, duration_s=DURATION_S,
                           orbit=orbit, motion=lambda t: figure.posed(*pose(t)))
