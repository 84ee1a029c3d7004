"""The live path's configuration, each default in one place: how online anchors run past a checkpoint's
span (``OnlineConfig``), and how a cold start's learner trains (``LearnConfig``).

The service's settings (``Settings.online_*``, ``EDMCGS_ONLINE_*``; their descriptions are the
documentation of each field) take their defaults from ``OnlineConfig`` and build one with
``Settings.online``; tests and benchmarks build one directly.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from edmcgs.errors import InvalidInputError
from edmcgs.protocol import TRANSITIONS


@dataclass(frozen=True)
class OnlineConfig:
    capacity: int = 64
    """Online anchors kept (older ones also expire with their events)."""
    fit_steps: int = 4
    """Adam steps correcting each anchor against its frame (0: predictions only)."""
    fit_lr: float = 6e-3
    """Their step size, as a fraction of the scene's extent."""
    fit_scale: float = 0.5
    """Fraction of the frame's size the correction renders and compares at."""
    colour_lr: float = 0.01
    """Step size of the per-Gaussian colour offsets each correction learns (0: none)."""
    transition: str = "select"
    """What moves the anchors: ``select`` (the candidate whose predictions were best) or one fixed."""
    finetune_steps: int = 0
    """Adam steps letting a copy of the transition learn from each correction (0: none)."""
    finetune_lr: float = 1e-4
    """Their step size."""
    spawn: int = 0
    """Static Gaussians at most added at each correction of an anchor-window checkpoint (0: none)."""
    project: bool = True
    """Renders of the event camera's own view are projected onto the events since their anchor's frame."""
    fit: bool = True
    """Correct in a background thread (False: predictions only, unless a caller fits by hand)."""

    def __post_init__(self):
        if self.transition not in TRANSITIONS:
            raise InvalidInputError(f"transition must be one of {', '.join(TRANSITIONS)}, "
                                    f"got {self.transition!r}")


@dataclass(frozen=True)
class LearnConfig:
    """How the learner of a cold start trains (``learner.py``); the service's ``EDMCGS_LEARN_*``
    settings build it."""

    workdir: Path = Path("edmcgs-learned")
    """Where it writes the checkpoints it publishes, and on stop ``learned.ckpt`` and ``learned.h5``."""
    intrinsics: tuple[float, float, float, float] | None = None
    """The frames' camera: fx, fy, cx, cy in pixels (None: estimated with the poses, else fx = fy = width,
    centred)."""
    contrast_threshold: float | None = None
    """The events' C, when the stream states it (else the preset's)."""
    trajectory: tuple[np.ndarray, np.ndarray] | None = None
    """The camera's poses (t_us [T], c2w [T, 4, 4]) when the stream states them (else ``poses`` decides)."""
    poses: str = "auto"
    """With no stated trajectory: ``auto``, structure from motion over each round's frames, the first
    round's anchor frames only (``edmcgs poses``: a camera that did not move is called static, one that
    only turned gets rotations); ``static``, the camera taken as still without looking."""
    preset: str = "auto"
    """The configuration trained (``edmcgs train --config``); ``auto``: ``moving`` for a camera that
    translates (its poses and 3D points from structure from motion), else ``real``."""
    overrides: tuple[str, ...] = ()
    """``key=value`` changes to it (``edmcgs train --set``)."""
    anchor_fps: float = 5.0
    """Frames at this rate are anchors; the others are held out and scored."""
    min_anchors: int = 3
    """Anchors before the first round."""
    first_steps: int = 150
    """Steps of the first round (then each round twice the one before, up to the preset's iterations)."""
    first_scale: float = 0.5
    """The first round renders and supervises at this fraction of the frames' size (a model live sooner;
    the later rounds train at the preset's)."""
    publish_s: float = 30.0
    """Seconds between two published checkpoints within a round (each round's end publishes too)."""
    eval_frames: int = 8
    """Held-out frames scored at each publication."""
    threads: int = 1
    """CPU threads of the learner process."""

    def __post_init__(self):
        if self.poses not in POSES:
            raise InvalidInputError(f"poses must be one of {', '.join(POSES)}, got {self.poses!r}")

    def presets(self) -> tuple[str, ...]:
        """Every preset a round may train (``auto``: either)."""
        return AUTO_PRESETS if self.preset == "auto" else (self.preset,)


POSES = ("auto", "static")
AUTO_PRESETS = ("real", "moving")
"""What ``preset="auto"`` picks from: a still or turning camera, a translating one."""
