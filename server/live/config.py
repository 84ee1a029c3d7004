"""How online anchors run past a checkpoint's span: the one place of their defaults.

The service's settings (``Settings.online_*``, ``EDMCGS_ONLINE_*``; their descriptions are the
documentation of each field) take their defaults from ``OnlineConfig`` and build one with
``Settings.online``; tests and benchmarks build one directly.
"""

from __future__ import annotations

from dataclasses import dataclass

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
