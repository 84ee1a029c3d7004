"""The one protocol every event source follows (live camera, AEDAT4 replay, HDF5 replay).

A source opens when constructed and is a context manager. ``read()`` returns the next
``SensorBatch`` (events, plus frames and IMU samples where the source has them) or None at the end
of the stream. ``info`` says the resolution and which streams exist; ``stats`` counts what boundary
validation dropped or reordered.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Protocol, runtime_checkable

import numpy as np

from edmcgs.errors import SensorError
from edmcgs.sensor.events import Events, EventStats
from edmcgs.sensor.frames import Frames


@dataclass(frozen=True)
class StreamInfo:
    """What a source delivers."""

    width: int
    """Event resolution, pixels."""
    height: int
    sensor: str
    """Camera name (model and serial) or a description of the file layout."""
    has_frames: bool
    """Whether batches can carry frames (APS / RGB)."""
    has_imu: bool
    """Whether batches can carry IMU samples."""
    live: bool
    """A camera (True) or a replay of a file (False)."""
    t_range_us: tuple[int, int] | None = None
    """First and last timestamp of a replay, on the file's clock; None for a camera."""
    frame_size: tuple[int, int] | None = None
    """(width, height) of the frames, when the source has frames."""


@dataclass(frozen=True)
class Extras:
    """What a recording states beside its streams (a ROS bag's or the RPG layout's calibration and ground
    truth, our HDF5's camera and threshold); empty for a camera and for most files."""

    intrinsics: tuple[float, float, float, float] | None = None
    """fx, fy, cx, cy in pixels at the event resolution."""
    distortion: tuple[float, ...] | None = None
    """The lens distortion the file states beside them (OpenCV order), not undone by a pinhole model."""
    trajectory_t_us: np.ndarray | None = None
    """int64 [T]: times of the ground-truth camera poses, on the stream clock."""
    trajectory_c2w: np.ndarray | None = None
    """float64 [T, 4, 4]: camera-to-world poses at trajectory_t_us."""
    contrast_threshold: float | None = None
    """The events' contrast threshold C, when the recording states it."""


@dataclass(frozen=True)
class SensorBatch:
    """One read from a source, all times int64 µs on the stream clock (after any loop shift)."""

    events: Events
    frames: Frames | None = None
    """Frames whose timestamps fall in this batch (RGB or grey, uint8 [F, H, W, C])."""
    imu: np.ndarray | None = None
    """IMU_DTYPE [K] samples in this batch."""
    t_end_us: int | None = None
    """Every event of the stream with t < t_end_us has now been delivered (None: only up to the last
    event's time, as for a live camera)."""
    loop: int = 0
    """Replays: how many times the recording has wrapped around."""
    time_shift_us: int = 0
    """Replays: added to the file's timestamps (each loop's, so that time keeps increasing)."""

    def shifted(self, dt_us: int) -> SensorBatch:
        """Every time of the batch ``dt_us`` later (images and samples shared, times copied)."""
        if not dt_us:
            return self
        imu = None
        if self.imu is not None:
            imu = self.imu.copy()
            imu["t"] += np.int64(dt_us)
        return replace(self, events=self.events.shifted(dt_us),
                       frames=None if self.frames is None else self.frames.shifted(dt_us), imu=imu,
                       t_end_us=None if self.t_end_us is None else self.t_end_us + int(dt_us),
                       time_shift_us=self.time_shift_us + int(dt_us))


@runtime_checkable
class EventSource(Protocol):
    """Structural type of every source; see the module docstring."""

    @property
    def info(self) -> StreamInfo: ...

    @property
    def stats(self) -> EventStats: ...

    def read(self) -> SensorBatch | None: ...

    def close(self) -> None: ...

    def __enter__(self) -> EventSource: ...

    def __exit__(self, *exc) -> None: ...


class SourceBase:
    """Shared plumbing: context manager, closed-state check, validation counts."""

    def __init__(self) -> None:
        self._stats = EventStats()
        self._closed = False
        self._extras = Extras()

    @property
    def stats(self) -> EventStats:
        return self._stats

    @property
    def extras(self) -> Extras:
        """Calibration and ground truth the recording states (``Extras()`` when none)."""
        return self._extras

    @property
    def closed(self) -> bool:
        return self._closed

    def _check_open(self) -> None:
        if self._closed:
            raise SensorError(f"{type(self).__name__} is closed")

    def close(self) -> None:
        self._closed = True

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()
