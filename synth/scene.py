"""Procedural dynamic scenes: Gaussians and camera as analytic functions of time, so any instant has
ground truth. The four scenes (``SCENES``) each live in their own module with a ``make(size)``.
"""

from __future__ import annotations

import importlib
import math
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Protocol

import numpy as np

from edmcgs.errors import InvalidInputError
from edmcgs.geometry import Intrinsics, world_to_camera
from edmcgs.model.render.rasterize_fast import rasterize_fast
from edmcgs.synth.cloud import Cloud
from edmcgs.synth.orbit import DAVIS346, Orbit

SCENES = ("jumpingjack", "kick", "mutant", "lego")
"""Scene names; scene ``name`` is built by ``edmcgs.synth.<name>.make(size)``."""

BACKGROUND = (0.55, 0.56, 0.6)
"""Constant background colour of every scene (linear RGB)."""


@dataclass(frozen=True)
class Size:
    """A resolution and the Gaussian density that goes with it."""

    name: str
    width: int
    height: int
    spacing_scale: float
    """Multiplies each scene's full-size surface spacing: coarser surfaces, fewer Gaussians."""

    @property
    def intrinsics(self) -> Intrinsics:
        return DAVIS346.scaled(self.width, self.height)


SIZES = {
    "small": Size("small", 173, 130, 1.6),  # half the DAVIS346 resolution, ~2.5x fewer Gaussians
    "full": Size("full", 346, 260, 1.0),
}


class Scene(Protocol):
    """What the dataset builder needs of a scene."""

    name: str
    intrinsics: Intrinsics
    duration_s: float
    background: tuple[float, float, float]

    def gaussians_at(self, t_s: float) -> Cloud:
        """The Gaussians at scene time t_s (seconds), float32."""

    def camera_at(self, t_s: float) -> np.ndarray:
        """Camera-to-world float64 [4, 4] (OpenCV convention) at scene time t_s."""


@dataclass(frozen=True)
class ProceduralScene:
    """A scene whose Gaussians come from ``motion(t_s)`` and whose camera follows ``orbit``."""

    name: str
    intrinsics: Intrinsics
    duration_s: float
    orbit: Orbit
    motion: Callable[[float], Cloud]
    background: tuple[float, float, float] = BACKGROUND

    def gaussians_at(self, t_s: float) -> Cloud:
        t_s = _check_t(t_s)
        return self.motion(t_s).as_float32()

    def camera_at(self, t_s: float) -> np.ndarray:
        return self.orbit.c2w(_check_t(t_s))


def _check_t(t_s) -> float:
    t_s = float(t_s)
    if not math.isfinite(t_s):
        raise InvalidInputError(f"t_s must be a finite time in seconds, got {t_s!r}")
    return t_s


CAMERAS = ("orbit", "sweep")
"""How a scene's camera goes on past the scene's own duration (``Orbit``): circling on, or sweeping back
over the same arc."""


def make_scene(name: str, size: str = "small", camera: str = "orbit") -> ProceduralScene:
    """Build scene ``name`` (one of ``SCENES``) at ``size`` ("small" or "full"), its camera one of
    ``CAMERAS``."""
    if name not in SCENES:
        raise InvalidInputError(f"unknown scene {name!r}; choose one of {', '.join(SCENES)}")
    if size not in SIZES:
        raise InvalidInputError(f"unknown size {size!r}; choose one of {', '.join(SIZES)}")
    if camera not in CAMERAS:
        raise InvalidInputError(f"unknown camera {camera!r}; choose one of {', '.join(CAMERAS)}")
    scene = importlib.import_module(f"edmcgs.synth.{name}").make(SIZES[size])
    return replace(scene, orbit=replace(scene.orbit, sweep=camera == "sweep"))


def render(scene: Scene, t_s: float, c2w: np.ndarray | None = None) -> np.ndarray:
    """The scene at t_s seen by its camera (or by ``c2w``): float32 [H, W, 3] in [0, 1]."""
    g = scene.gaussians_at(t_s)
    w2c = world_to_camera(scene.camera_at(t_s) if c2w is None else c2w)
    out = rasterize_fast(g.means, g.quats, g.scales, g.opacities, g.colors, w2c.astype(np.float32),
                         scene.intrinsics, background=np.asarray(scene.background, np.float32))
    return np.clip(out.image, 0.0, 1.0)
