"""AEDAT4 replay through dv-processing's ``MonoCameraRecording``: events, and frames and IMU when present.

Trigger and other streams are skipped. Files are read forward packet by packet (never whole).
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from pathlib import Path

import dv_processing as dv
import numpy as np

from edmcgs.errors import ReplayFormatError
from edmcgs.sensor.frames import Frames
from edmcgs.sensor.sources.base import StreamInfo
from edmcgs.sensor.sources.dv_bridge import dv_error_text, frame_image, imu_array, store_columns
from edmcgs.sensor.sources.pacing import Pacing
from edmcgs.sensor.sources.replay import Chunk, Replay


class AedatReplay(Replay):
    """Replay an .aedat4 file. ``pacing`` sets speed, start offset, looping and batch length."""

    def __init__(self, path: str | os.PathLike, pacing: Pacing | None = None, **kwargs) -> None:
        super().__init__(pacing, **kwargs)
        self.path = Path(path)
        if not self.path.is_file():
            raise ReplayFormatError(f"{self.path}: no such file")
        self._rec = self._call("open", lambda: dv.io.MonoCameraRecording(str(self.path)))
        rec = self._rec
        if not rec.isEventStreamAvailable():
            raise ReplayFormatError(f"{self.path}: no event stream (streams: {rec.getStreamNames()})")
        width, height = rec.getEventResolution()
        self._has_frames = bool(rec.isFrameStreamAvailable())
        self._has_imu = bool(rec.isImuStreamAvailable())
        t_range = self._call("read the time range", rec.getTimeRange)
        self._info = StreamInfo(
            width=int(width), height=int(height), sensor=rec.getCameraName(), has_frames=self._has_frames,
            has_imu=self._has_imu, live=False, t_range_us=(int(t_range[0]), int(t_range[1])),
            frame_size=tuple(int(v) for v in rec.getFrameResolution()) if self._has_frames else None)

    def _call(self, what: str, fn):
        try:
            return fn()
        except (RuntimeError, IndexError, ValueError) as exc:
            raise ReplayFormatError(f"{self.path}: cannot {what} (not AEDAT4, truncated or corrupt?): "
                                    f"{dv_error_text(exc)}") from exc

    def _chunks(self, begin_us: int) -> Iterator[Chunk]:
        rec = self._rec
        self._call("rewind", rec.resetSequentialRead)
        next_frame = self._call("read a frame", rec.getNextFrame) if self._has_frames else None
        pending_imu: list[np.ndarray] = []
        imu_done = not self._has_imu
        while True:
            store = self._call("read events", rec.getNextEventBatch)
            if store is None:
                horizon = 2**62
                t = x = y = p = np.empty(0, np.int64)
            else:
                t, x, y, p = store_columns(store)
                if len(t) and t[-1] < begin_us:
                    continue  # before the start offset: skip without decoding frames one by one
                horizon = int(t[-1]) if len(t) else begin_us  # more events at t[-1] may follow
            events = self._validated(t, x, y, p)
            frames = []
            while next_frame is not None and next_frame.timestamp < horizon:
                frames.append((int(next_frame.timestamp), frame_image(next_frame)))
                next_frame = self._call("read a frame", rec.getNextFrame)
            while not imu_done and (not pending_imu or pending_imu[-1]["t"][-1] < horizon):
                samples = self._call("read IMU samples", rec.getNextImuBatch)
                if samples is None:
                    imu_done = True
                elif len(samples):
                    pending_imu.append(imu_array(samples))
            imu = np.concatenate(pending_imu) if pending_imu else None
            if imu is not None:
                pending_imu = [imu[imu["t"] >= horizon]] if np.any(imu["t"] >= horizon) else []
                imu = imu[imu["t"] < horizon]
            yield Chunk(events=events, frames=_frames(frames), imu=imu, horizon_us=horizon)
            if store is None:
                return

    def close(self) -> None:
        super().close()
        self._rec = None  # dv closes the file when the reader is released


def _frames(items: list[tuple[int, np.ndarray]]) -> Frames | None:
    if not items:
        return None
    return Frames([t for t, _ in items], np.stack([img for _, img in items]))
