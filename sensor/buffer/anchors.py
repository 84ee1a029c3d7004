"""The anchor store: the RGB/APS frames with their timestamps, answering tau(t) = last anchor <= t.

The event map for time t accumulates events over the half-open [tau(t), t) (paper, section 3.3: an
event at t belongs to the next window), so every query needs the anchor at or before t. The store
keeps the newest ``capacity`` anchors; asking for one that was evicted raises ``WindowUnavailable``
instead of silently answering with a later anchor.
"""

from __future__ import annotations

import bisect
import threading
from dataclasses import dataclass

import numpy as np

from edmcgs.errors import InvalidInputError, WindowUnavailable
from edmcgs.sensor.frames import Frames


@dataclass(frozen=True)
class Anchor:
    t_us: int
    """Exposure time of the frame, int64 µs on the event clock."""
    image: np.ndarray
    """uint8 [H, W, C], C = 1 grey or 3 RGB."""
    pose: np.ndarray | None = None
    """float64 [4, 4] camera-to-world, when known."""


class AnchorStore:
    """Thread-safe: one writer (the ingest loop), many readers (render requests)."""

    def __init__(self, capacity: int = 1024) -> None:
        if isinstance(capacity, bool) or int(capacity) != capacity or capacity <= 0:
            raise InvalidInputError(f"capacity must be a positive integer, got {capacity!r}")
        self.capacity = int(capacity)
        self._times: list[int] = []
        self._anchors: list[Anchor] = []
        self._lock = threading.Lock()
        self._evicted_max_t: int | None = None
        self.evicted = 0

    def add(self, t_us: int, image: np.ndarray, pose: np.ndarray | None = None) -> None:
        """Append an anchor; it must be later than the newest one."""
        image = np.asarray(image)
        if image.ndim == 2:
            image = image[..., None]
        if image.dtype != np.uint8 or image.ndim != 3 or image.shape[2] not in (1, 3):
            raise InvalidInputError(f"anchor image must be uint8 [H, W, C] with C in (1, 3), "
                                    f"got {image.dtype} {image.shape}")
        if pose is not None:
            pose = np.asarray(pose, np.float64)
            if pose.shape != (4, 4) or not np.isfinite(pose).all():
                raise InvalidInputError(f"anchor pose must be a finite 4x4 matrix, got shape {pose.shape}")
        t_us = int(t_us)
        with self._lock:
            if self._times and t_us <= self._times[-1]:
                raise InvalidInputError(
                    f"anchor at {t_us} µs is not after the newest one ({self._times[-1]} µs)")
            self._times.append(t_us)
            self._anchors.append(Anchor(t_us, image, pose))
            extra = len(self._times) - self.capacity
            if extra > 0:
                self._evicted_max_t = self._times[extra - 1]
                del self._times[:extra], self._anchors[:extra]
                self.evicted += extra

    def add_frames(self, frames: Frames) -> None:
        for i in range(len(frames)):
            self.add(int(frames.t_us[i]), frames.images[i], None if frames.poses is None else frames.poses[i])

    def tau(self, t_us: int) -> int | None:
        """Time of the last anchor at or before t_us; None when t_us precedes every anchor ever added."""
        with self._lock:
            return self._find(int(t_us)).t_us if self._has_anchor_for(int(t_us)) else None

    def anchor_at(self, t_us: int) -> Anchor:
        """The last anchor at or before t_us, or ``WindowUnavailable`` saying why there is none."""
        t_us = int(t_us)
        with self._lock:
            if not self._has_anchor_for(t_us):
                first = (f"the first anchor is at {self._times[0]} µs" if self._times
                         else "no anchor received yet")
                raise WindowUnavailable(f"no anchor frame at or before {t_us} µs: {first}")
            return self._find(t_us)

    def _has_anchor_for(self, t_us: int) -> bool:
        """Lock held. Raises if the answer was evicted."""
        i = bisect.bisect_right(self._times, t_us)
        if i > 0:
            return True
        if self._evicted_max_t is not None:
            raise WindowUnavailable(
                f"the anchor for {t_us} µs was evicted: the store keeps the newest {self.capacity} anchors, "
                f"now from {self._times[0]} µs")
        return False

    def _find(self, t_us: int) -> Anchor:
        return self._anchors[bisect.bisect_right(self._times, t_us) - 1]

    def next_after(self, t_us: int) -> int | None:
        """Time of the first anchor strictly after t_us (the end of t_us's anchor interval), if any."""
        with self._lock:
            i = bisect.bisect_right(self._times, int(t_us))
            return self._times[i] if i < len(self._times) else None

    def times(self) -> np.ndarray:
        """int64 [F]: the retained anchor times."""
        with self._lock:
            return np.array(self._times, np.int64)

    @property
    def latest(self) -> Anchor | None:
        with self._lock:
            return self._anchors[-1] if self._anchors else None

    def __len__(self) -> int:
        return len(self._times)
