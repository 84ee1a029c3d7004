"""``kick``: a figure throwing front kicks with its right leg (localised limb motion).

A kick (chamber, snap out, re-chamber, set down) takes 0.35 s of every ``PERIOD_S`` = 0.5 s; the rest
of the body holds a guard and only leans and sways a little. Between two anchors at 5 fps the leg
goes through most of a kick, which a smooth interpolator in time cannot recover.
"""

from __future__ import annotations

import numpy as np

from edmcgs.synth.cloud import rotation
from edmcgs.synth.figure import ROOT_HEIGHT, Figure
from edmcgs.synth.orbit import Orbit
from edmcgs.synth.scene import ProceduralScene, Size

PERIOD_S = 0.5
KICK_S = 0.35
DURATION_S = 2.0
SPACING_M = 0.02
PALETTE = {
    "shirt_a": (0.1, 0.12, 0.14), "shirt_b": (0.9, 0.9, 0.92),
    "arm_a": (0.9, 0.9, 0.92), "arm_b": (0.55, 0.1, 0.45),
    "leg_a": (0.95, 0.55, 0.1), "leg_b": (0.15, 0.15, 0.45),
    "hair": (0.6, 0.35, 0.1),
}


def pose(t_s: float) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """Local bone rotations and the pelvis position at t_s."""
    u = (t_s % PERIOD_S) / KICK_S  # in [0, 1] during a kick
    active = u < 1.0
    kick = np.sin(np.pi * u) ** 2 if active else 0.0  # hip flexion, 0 -> 1 -> 0, smooth at both ends
    chamber = np.sin(2 * np.pi * u) ** 2 if active else 0.0  # knee bent on the way up and down
    hip = np.radians(95) * kick
    knee = np.radians(100) * chamber
    sway = np.sin(2 * np.pi * t_s / PERIOD_S)
    local = {
        "torso": rotation("x", np.radians(-14) * kick) @ rotation("z", np.radians(6) * sway),
        "head": rotation("x", np.radians(10) * kick),
        "thigh_r": rotation("x", -hip), "shin_r": rotation("x", knee),
        "thigh_l": rotation("x", np.radians(-8) * kick), "shin_l": rotation("x", np.radians(14) * kick),
        "upper_arm_l": rotation("x", np.radians(-35 - 20 * kick)) @ rotation("y", np.radians(-15)),
        "forearm_l": rotation("x", np.radians(-105)),
        "upper_arm_r": rotation("x", np.radians(-30 + 45 * kick)) @ rotation("y", np.radians(20)),
        "forearm_r": rotation("x", np.radians(-100 + 40 * kick)),
    }
    root = np.array([0.0, 0.02 * kick, ROOT_HEIGHT - 0.03 * kick])
    return local, root


def make(size: Size) -> ProceduralScene:
    figure = Figure(SPACING_M * size.spacing_scale, PALETTE)
    orbit = Orbit(target=(0.0, -0.45, 0.95), radius=2.7, elevation_deg=10.0,
                  azimuth_start_deg=-80.0, azimuth_end_deg=-45.0, duration_s=DURATION_S)
    return ProceduralScene(name="kick", intrinsics=size.intrinsics, duration_s=DURATION_S,
                           orbit=orbit, motion=lambda t: figure.posed(*pose(t)))
