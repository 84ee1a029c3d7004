"""HDF5 replay: our recordings, DSEC and v2e files, layout detected automatically, read lazily in chunks.

Layouts:

- **edmcgs recording** (``sensor/files/recording.py``): events and anchor frames.
- **DSEC** (``events.h5`` of the DSEC dataset): ``events/x``, ``events/y`` uint16, ``events/p`` uint8
  0/1, ``events/t`` uint32 µs relative to the scalar ``t_offset`` (int64 µs), and ``ms_to_idx``.
  The resolution is not stored: 640 x 480 (DSEC's event cameras) unless ``resolution`` is given.
- **v2e** (SensorsINI/v2e ``--dvs_h5``): ``events`` uint32 [N, 4], columns t, x, y, p with t in
  *microseconds* from the start of the video (v2e multiplies its float seconds by 1e6 before casting)
  and p 0 (OFF) / 1 (ON); optionally ``frame`` uint8 [F, H, W] with ``frame_ts`` (µs). The resolution
  comes from ``resolution``, else from ``frame``, else from one chunked pass over x and y.

Memory holds about one chunk of ``chunk_events`` events (or one batch window, if that is longer);
a start offset is found by binary search on the file's time column (O(log N) reads), so a multi-GB
file is never loaded whole.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from pathlib import Path

import h5py
import numpy as np

from edmcgs.errors import InvalidInputError, ReplayFormatError, translated
from edmcgs.sensor.events import Events
from edmcgs.sensor.files.recording import RecordingFile, is_recording, open_hdf5
from edmcgs.sensor.frames import Frames
from edmcgs.sensor.sources.base import Extras, StreamInfo
from edmcgs.sensor.sources.pacing import Pacing
from edmcgs.sensor.sources.replay import Chunk, Replay

SUPPORTED_LAYOUTS = (
    "edmcgs recording (attribute format='edmcgs.recording')",
    "DSEC (events/x, events/y, events/p, events/t + t_offset [+ ms_to_idx])",
    "v2e (events [N, 4] = t µs, x, y, p)",
)
DSEC_RESOLUTION = (640, 480)


class _Layout:
    """How to read one file layout: event count, raw columns by index range, time at an index, frames."""

    name: str
    n: int
    width: int
    height: int
    sensor: str

    def columns(self, i0: int, i1: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        raise NotImplementedError

    def time_at(self, i: int) -> int:
        raise NotImplementedError

    def frame_times(self) -> np.ndarray | None:
        return None

    def frame_images(self, i0: int, i1: int) -> np.ndarray:
        raise NotImplementedError

    def extras(self) -> Extras:
        return Extras()

    def close(self) -> None:
        pass


class _Ours(_Layout):
    name = "edmcgs recording"

    def __init__(self, path: Path) -> None:
        self._rec = RecordingFile(path)
        self.n, self.width, self.height = self._rec.n_events, self._rec.width, self._rec.height
        self.sensor = self._rec.sensor
        self._t = self._rec.event_columns["t"]

    def columns(self, i0, i1):
        return self._rec.read_event_columns(i0, i1)

    def time_at(self, i):
        return int(self._t[i])

    def frame_times(self):
        return self._rec.frame_times("anchors")

    def frame_images(self, i0, i1):
        return self._rec.frame_images(i0, i1, "anchors")

    def extras(self):
        intr, (traj_t, traj_c2w) = self._rec.intrinsics(), self._rec.trajectory()
        return Extras(intrinsics=None if intr is None else tuple(float(v) for v in intr),
                      trajectory_t_us=traj_t, trajectory_c2w=traj_c2w,
                      contrast_threshold=self._rec.contrast_threshold)

    def close(self):
        self._rec.close()


class _Dsec(_Layout):
    name = "DSEC"

    def __init__(self, f: h5py.File, resolution: tuple[int, int] | None) -> None:
        g = f["events"]
        self._cols = [g[k] for k in "txyp"]
        if len({len(c) for c in self._cols}) != 1:
            raise ReplayFormatError(f"DSEC event columns differ in length: {[len(c) for c in self._cols]}")
        self._offset = int(f["t_offset"][()]) if "t_offset" in f else 0
        self.n = len(self._cols[0])
        self.width, self.height = resolution or DSEC_RESOLUTION
        self.sensor = "DSEC event camera"

    def columns(self, i0, i1):
        t, x, y, p = (c[i0:i1] for c in self._cols)
        return t.astype(np.int64) + self._offset, x, y, p

    def time_at(self, i):
        return int(self._cols[0][i]) + self._offset


class _V2e(_Layout):
    name = "v2e"

    def __init__(self, f: h5py.File, resolution: tuple[int, int] | None, chunk: int) -> None:
        self._ev = f["events"]
        self.n = len(self._ev)
        frame, frame_ts = f.get("frame"), f.get("frame_ts")
        self._frame = frame if isinstance(frame, h5py.Dataset) and frame.ndim == 3 and \
            isinstance(frame_ts, h5py.Dataset) and len(frame_ts) == len(frame) else None
        self._frame_ts = frame_ts if self._frame is not None else None
        if resolution is not None:
            self.width, self.height = resolution
        elif self._frame is not None:
            self.height, self.width = self._frame.shape[1:]
        else:  # not stored: the smallest sensor that holds every event, found in one chunked pass
            mx = my = -1
            for i in range(0, self.n, chunk):
                rows = self._ev[i:i + chunk]
                mx, my = max(mx, int(rows[:, 1].max())), max(my, int(rows[:, 2].max()))
            self.width, self.height = max(mx + 1, 1), max(my + 1, 1)
        self.sensor = "v2e simulation"

    def columns(self, i0, i1):
        rows = self._ev[i0:i1]
        return rows[:, 0].astype(np.int64), rows[:, 1], rows[:, 2], rows[:, 3]

    def time_at(self, i):
        return int(self._ev[i, 0])

    def frame_times(self):
        return None if self._frame_ts is None else self._frame_ts[:].astype(np.int64)

    def frame_images(self, i0, i1):
        return self._frame[i0:i1]


def _all_keys(f: h5py.File) -> list[str]:
    names: list[str] = []
    f.visit(names.append)
    return names


def _detect(path: Path, f: h5py.File, resolution, chunk: int) -> _Layout:
    if is_recording(f):
        return _Ours(path)
    ev = f.get("events")
    if isinstance(ev, h5py.Group) and all(isinstance(ev.get(k), h5py.Dataset) for k in "xypt"):
        return _Dsec(f, resolution)
    if isinstance(ev, h5py.Dataset) and ev.ndim == 2 and ev.shape[1] == 4:
        return _V2e(f, resolution, chunk)
    keys = _all_keys(f)
    shown = ", ".join(keys[:30]) + (f", ... ({len(keys)} in all)" if len(keys) > 30 else "")
    raise ReplayFormatError(f"{path}: unknown HDF5 event layout; keys found: [{shown}]; supported layouts: "
                            + "; ".join(SUPPORTED_LAYOUTS))


class Hdf5Replay(Replay):
    """Replay an HDF5 event file (see the module docstring for the layouts).

    ``resolution``: (width, height) for layouts that do not store it (DSEC, v2e without frames).
    ``chunk_events``: events read per step, which bounds memory.
    """

    def __init__(self, path: str | os.PathLike, pacing: Pacing | None = None, *,
                 resolution: tuple[int, int] | None = None, chunk_events: int = 1 << 20, **kwargs) -> None:
        super().__init__(pacing, **kwargs)
        self.path = Path(path)
        if resolution is not None and (len(resolution) != 2 or min(resolution) <= 0):
            raise InvalidInputError(f"resolution must be (width, height) > 0, got {resolution!r}")
        if chunk_events <= 0:
            raise InvalidInputError(f"chunk_events must be positive, got {chunk_events}")
        self.chunk_events = int(chunk_events)
        self._f = open_hdf5(self.path)
        try:
            self._layout = self._read("detect the layout", lambda: _detect(self.path, self._f, resolution,
                                                                            self.chunk_events))
            self._frame_t = self._read("read frame times", self._layout.frame_times)
            self._extras = self._read("read the camera", self._layout.extras)
            self._info = StreamInfo(
                width=int(self._layout.width), height=int(self._layout.height),
                sensor=self._layout.sensor, has_frames=self._frame_t is not None and len(self._frame_t) > 0,
                has_imu=False, live=False, t_range_us=self._read("read the time range", self._time_range),
                frame_size=(int(self._layout.width), int(self._layout.height)) if self._frame_t is not None
                else None)
        except BaseException:
            self._close_files()
            raise

    @property
    def layout(self) -> str:
        return self._layout.name

    def _read(self, what: str, fn):
        # InvalidInputError passes: it says what was asked wrong (a resolution), not what the file is.
        def corrupt(exc: BaseException) -> ReplayFormatError:
            return ReplayFormatError(f"{self.path}: cannot {what} (truncated or corrupt?): {exc}")

        with translated((OSError, KeyError, ValueError, TypeError, IndexError), corrupt,
                        keep=(ReplayFormatError, InvalidInputError)):
            return fn()

    def _time_range(self) -> tuple[int, int] | None:
        ends = []
        if self._layout.n:
            ends += [self._layout.time_at(0), self._layout.time_at(self._layout.n - 1)]
        if self._frame_t is not None and len(self._frame_t):
            ends += [int(self._frame_t[0]), int(self._frame_t[-1])]
        return (min(ends), max(ends)) if ends else None

    def _search(self, t_us: int) -> int:
        """First event index with t >= t_us, by binary search on the file (O(log N) reads)."""
        lo, hi = 0, self._layout.n
        while lo < hi:
            mid = (lo + hi) // 2
            if self._layout.time_at(mid) < t_us:
                lo = mid + 1
            else:
                hi = mid
        return lo

    def _chunks(self, begin_us: int) -> Iterator[Chunk]:
        lay, step = self._layout, self.chunk_events
        i = self._read("seek", lambda: self._search(begin_us))
        ft = self._frame_t if self._frame_t is not None else np.empty(0, np.int64)
        fi = int(np.searchsorted(ft, begin_us, side="left"))
        while i < lay.n:
            i1 = min(i + step, lay.n)
            cols = self._read(f"read events [{i}, {i1})", lambda i=i, i1=i1: lay.columns(i, i1))
            ev = self._validated(*cols)
            horizon = 2**62 if i1 == lay.n else self._read("read a timestamp", lambda i1=i1: lay.time_at(i1))
            fj = int(np.searchsorted(ft, horizon, side="left"))
            yield Chunk(events=ev, frames=self._frames(fi, fj), imu=None, horizon_us=horizon)
            i, fi = i1, fj
        if fi < len(ft):
            yield Chunk(events=Events.empty(), frames=self._frames(fi, len(ft)), imu=None, horizon_us=2**62)

    def _frames(self, i0: int, i1: int) -> Frames | None:
        if i1 <= i0:
            return None
        images = self._read("read frames", lambda: self._layout.frame_images(i0, i1))
        return self._read("read frames", lambda: Frames(self._frame_t[i0:i1], images))

    def _close_files(self) -> None:
        if getattr(self, "_layout", None) is not None:
            self._layout.close()
        self._f.close()

    def close(self) -> None:
        if not self.closed:
            self._close_files()
        super().close()
