"""What every replay shares: cutting a file's data into fixed-length batches, pacing and looping.

A concrete replay (AEDAT4, HDF5) only says how to read its file forward in chunks (``_chunks``),
validated through ``_validated``; this base turns the chunks into batches of ``pacing.batch_us`` of
recording time, each marked complete up to its end, paced on the wall clock and, when looping,
shifted by the recording's length each time round so that timestamps keep increasing.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass

import numpy as np

from edmcgs.errors import InvalidInputError
from edmcgs.geometry import Trajectory
from edmcgs.sensor.events import DEFAULT_MAX_DISORDER_US, Events
from edmcgs.sensor.frames import Frames
from edmcgs.sensor.sources.base import SensorBatch, SourceBase, StreamInfo
from edmcgs.sensor.sources.pacing import Pacer, Pacing

_FOREVER = 2**62  # a time bound past any real timestamp


@dataclass(frozen=True)
class Chunk:
    """A piece of a file read forward, on the file's clock."""

    events: Events
    frames: Frames | None
    imu: np.ndarray | None
    horizon_us: int
    """Everything with t < horizon_us has been delivered by this chunk and the ones before."""


class Ahead:
    """Timed items ``(t_us, item)`` from an iterator in time order, handed out up to a horizon: a file's
    slower streams (frames, IMU) read alongside its events."""

    def __init__(self, items: Iterator[tuple[int, object]]) -> None:
        self._items = items
        self._next = next(items, None)

    def until(self, horizon_us: int) -> list[tuple[int, object]]:
        """Every item with t < horizon_us not handed out yet."""
        out = []
        while self._next is not None and self._next[0] < horizon_us:
            out.append(self._next)
            self._next = next(self._items, None)
        return out


class Replay(SourceBase):
    """Base of file replays. Subclasses set ``_info`` (with ``t_range_us`` covering every stream) and
    implement ``_chunks(begin_us)``, which reads from the start (or ``begin_us``) every time it is called.
    """

    _info: StreamInfo

    def __init__(self, pacing: Pacing | None = None, *, max_disorder_us: int = DEFAULT_MAX_DISORDER_US,
                 clock: Callable[[], float] = time.monotonic, sleep: Callable[[float], None] = time.sleep):
        super().__init__()
        self.pacing = Pacing() if pacing is None else pacing
        if not isinstance(self.pacing, Pacing):
            raise InvalidInputError(f"pacing must be a Pacing, got {type(self.pacing).__name__}")
        self.max_disorder_us = max_disorder_us
        self._pacer = Pacer(self.pacing.factor, clock=clock, sleep=sleep)
        self._batches_iter: Iterator[SensorBatch] | None = None
        self._last_t: int | None = None
        self._trajectory: Trajectory | None = None

    @property
    def info(self) -> StreamInfo:
        return self._info

    @property
    def pacer(self) -> Pacer:
        return self._pacer

    def _posed(self, frames: Frames) -> Frames:
        """``frames`` with the poses the recording states for them (its trajectory at their times, on the
        file's clock), so that a frame past a checkpoint's span says where the camera is. All or none of a
        replay's frames are posed: only a trajectory over the whole recording poses them (a ground truth
        that starts late, as a motion-capture one may, would leave some frames without)."""
        ex, span = self.extras, self._info.t_range_us
        if frames.poses is not None or ex.trajectory_t_us is None or len(ex.trajectory_t_us) < 2 \
                or span is None or span[0] < ex.trajectory_t_us[0] or span[1] > ex.trajectory_t_us[-1]:
            return frames
        if self._trajectory is None:
            self._trajectory = Trajectory(ex.trajectory_t_us, ex.trajectory_c2w)
        return Frames(frames.t_us, frames.images, self._trajectory.at(frames.t_us))

    def _chunks(self, begin_us: int) -> Iterator[Chunk]:
        raise NotImplementedError

    def _validated(self, t, x, y, p) -> Events:
        """Raw columns -> Events, counting what was dropped (later than what was already emitted)."""
        ev, st = Events.from_arrays(t, x, y, p, width=self._info.width, height=self._info.height,
                                    max_disorder_us=self.max_disorder_us, not_before_us=self._last_t)
        self._stats.add(st)
        if len(ev):
            self._last_t = ev.t_end
        return ev

    def read(self) -> SensorBatch | None:
        """The next batch, once it is due on the wall clock; None at the end (never, when looping)."""
        self._check_open()
        if self._batches_iter is None:
            self._batches_iter = self._batches()
        batch = next(self._batches_iter, None)
        if batch is not None:
            self._pacer.wait_until(batch.t_end_us)
        return batch

    def __iter__(self) -> Iterator[SensorBatch]:
        while (batch := self.read()) is not None:
            yield batch

    def _batches(self) -> Iterator[SensorBatch]:
        if self._info.t_range_us is None:
            return
        t_first, t_last = self._info.t_range_us
        begin = t_first + int(self.pacing.start_offset_us)
        if begin > t_last:
            raise InvalidInputError(f"start offset {self.pacing.start_offset_us} µs is past the end of the "
                                    f"recording ({t_last - t_first} µs long)")
        end = t_last + 1
        self._pacer.wait_until(begin)  # fixes the wall-clock origin
        loop = 0
        while True:
            self._last_t = None
            yield from self._windows(begin, end, loop, loop * (end - begin))
            if not self.pacing.loop:
                return
            loop += 1

    def _windows(self, begin: int, end: int, loop: int, shift: int) -> Iterator[SensorBatch]:
        step = int(self.pacing.batch_us)
        buf, pos = Events.empty(), 0
        frames: list[Frames] = []
        imu: list[np.ndarray] = []
        w0 = begin

        def next_data_time() -> int | None:
            times = [int(buf.t[pos])] if pos < len(buf) else []
            times += [int(f.t_us[0]) for f in frames[:1]] + [int(a["t"][0]) for a in imu[:1]]
            return min(times) if times else None

        def take(w1: int) -> SensorBatch:
            nonlocal pos, frames, imu
            i1 = pos + int(np.searchsorted(buf.t[pos:], w1, side="left"))
            ev = buf[pos:i1]
            pos = i1
            got_frames = [f.time_slice(-_FOREVER, w1) for f in frames]
            frames = [f.time_slice(w1, _FOREVER) for f in frames]
            frames = [f for f in frames if len(f)]
            got_frames = [f for f in got_frames if len(f)]
            got_imu = [a[a["t"] < w1] for a in imu]
            imu = [a[a["t"] >= w1] for a in imu if np.any(a["t"] >= w1)]
            got_imu = [a for a in got_imu if len(a)]
            fr = self._posed(Frames.concat(got_frames)) if got_frames else None
            im = np.concatenate(got_imu) if got_imu else None
            return SensorBatch(events=ev, frames=fr, imu=im, t_end_us=w1, loop=loop).shifted(shift)

        def windows_until(horizon: int) -> Iterator[SensorBatch]:
            nonlocal w0
            while True:
                nxt = next_data_time()
                nxt = horizon if nxt is None else min(nxt, horizon)
                if nxt >= w0 + step:  # skip windows known to be empty
                    w0 += (nxt - w0) // step * step
                if w0 + step > horizon:
                    return
                yield take(w0 + step)
                w0 += step

        for chunk in self._chunks(begin):
            # data before `begin` is skipped on purpose (start offset), not dropped
            ev = chunk.events.time_slice(begin, _FOREVER)
            if len(ev):
                buf, pos = Events.concat([buf[pos:], ev]), 0
            if chunk.frames is not None and len(fr := chunk.frames.time_slice(begin, _FOREVER)):
                frames.append(fr)
            if chunk.imu is not None and len(im := chunk.imu[chunk.imu["t"] >= begin]):
                imu.append(im)
            yield from windows_until(min(chunk.horizon_us, end))
        yield from windows_until(end)
        if w0 < end:  # the last partial window carries completeness up to the end
            yield take(end)
        if next_data_time() is not None:  # data past the stated time range: delivered, not lost
            last = max([int(buf.t[-1])] * (pos < len(buf)) + [int(f.t_us[-1]) for f in frames]
                       + [int(a["t"].max()) for a in imu])
            yield take(last + 1)
