"""The AEDAT4 decoder process: dv-processing's ``MonoCameraRecording`` read forward, sent as plain arrays.

It runs in a child process because dv-processing's LZ4 decoder can spin forever on a corrupt packet
while holding the GIL: in the server's process that would stop HTTP, health and shutdown. The parent
(``edmcgs.sensor.sources.aedat``) starts it as ``python -m edmcgs.sensor.sources.aedat_decoder PATH FD``
(FD: its end of a socket pair) and kills a child that stays silent too long.

Messages on the pipe, child to parent: ``("hello",)`` once its imports are done, ``("info", dict)``
once the file is open, then per ``("read", begin_us)`` command
a run of ``("chunk", t, x, y, p, frames, imu, horizon_us)`` closed by ``("end",)``; any dv failure is
``("error", what, text)`` and ends the child. Frames travel as ``[(t_us, uint8 [H, W, C]), ...]``.
"""

from __future__ import annotations

import sys
from multiprocessing.connection import Connection

import dv_processing as dv
import numpy as np

from edmcgs.errors import translated
from edmcgs.sensor.sources.dv_bridge import dv_error_text, frame_image, imu_array, store_columns


class _Failed(Exception):
    def __init__(self, what: str, exc: BaseException):
        super().__init__(what)
        self.what, self.text = what, dv_error_text(exc)


def _call(what: str, fn):
    with translated((RuntimeError, IndexError, ValueError), lambda exc: _Failed(what, exc)):
        return fn()


def serve(path: str, conn) -> None:
    """Child entry point: open ``path``, send its info, then answer read commands until told to stop."""
    try:
        conn.send(("hello",))
        rec = _call("open", lambda: dv.io.MonoCameraRecording(path))
        info = _info(rec)
        conn.send(("info", info))
        if "resolution" not in info:
            return
        while (command := conn.recv())[0] == "read":
            for chunk in _chunks(rec, int(command[1])):
                conn.send(("chunk", *chunk))
            conn.send(("end",))
    except _Failed as failed:
        conn.send(("error", failed.what, failed.text))
    except (EOFError, BrokenPipeError, KeyboardInterrupt):
        pass  # the parent is gone or closing
    finally:
        conn.close()


def _info(rec) -> dict:
    """The file's streams; with events or frames (a frames-only file: an APS recording, its resolution
    the frames'), its resolution, camera, time range and what else it holds."""
    has_events, has_frames = bool(rec.isEventStreamAvailable()), bool(rec.isFrameStreamAvailable())
    info = {"streams": list(rec.getStreamNames()), "has_events": has_events}
    if has_events or has_frames:
        first, last = (int(v) for v in _call("read the time range", rec.getTimeRange))
        resolution = rec.getEventResolution() if has_events else rec.getFrameResolution()
        info.update(resolution=tuple(int(v) for v in resolution), sensor=rec.getCameraName(),
                    has_frames=has_frames, has_imu=bool(rec.isImuStreamAvailable()),
                    t_range=(min(first, *_first_items(rec)), last),
                    frame_size=tuple(int(v) for v in rec.getFrameResolution()) if has_frames else None)
    return info


def _first_items(rec) -> list[int]:
    """The time of each stream's first item: a frame's timestamp (mid-exposure) may precede the range
    the file's table states, and a replay must start at the earliest item of any stream."""
    times = []
    store = _call("read events", rec.getNextEventBatch) if rec.isEventStreamAvailable() else None
    if store is not None and len(store):
        times.append(int(store_columns(store)[0][0]))
    if rec.isFrameStreamAvailable() and (frame := _call("read a frame", rec.getNextFrame)) is not None:
        times.append(int(frame.timestamp))
    if rec.isImuStreamAvailable() and (imu := _call("read IMU samples", rec.getNextImuBatch)):
        times.append(int(imu[0].timestamp))
    _call("rewind", rec.resetSequentialRead)
    return times


def _chunks(rec, begin_us: int):
    """(t, x, y, p, frames, imu, horizon_us) pieces of the file from the start, skipping event packets
    that end before ``begin_us`` (the parent drops what else precedes the replay's start)."""
    _call("rewind", rec.resetSequentialRead)
    has_imu, has_events = bool(rec.isImuStreamAvailable()), bool(rec.isEventStreamAvailable())
    next_frame = _call("read a frame", rec.getNextFrame) if rec.isFrameStreamAvailable() else None
    pending_imu: list[np.ndarray] = []
    imu_done = not has_imu
    while True:
        store = _call("read events", rec.getNextEventBatch) if has_events else None  # none: all at once
        if store is None:
            horizon = 2**62
            t = x = y = p = np.empty(0, np.int64)
        else:
            t, x, y, p = store_columns(store)
            if len(t) and t[-1] < begin_us:
                continue  # before the start offset: skip without decoding frames one by one
            horizon = int(t[-1]) if len(t) else begin_us  # more events at t[-1] may follow
        frames = []
        while next_frame is not None and next_frame.timestamp < horizon:
            frames.append((int(next_frame.timestamp), frame_image(next_frame)))
            next_frame = _call("read a frame", rec.getNextFrame)
        while not imu_done and (not pending_imu or pending_imu[-1]["t"][-1] < horizon):
            samples = _call("read IMU samples", rec.getNextImuBatch)
            if samples is None:
                imu_done = True
            elif len(samples):
                pending_imu.append(imu_array(samples))
        imu = np.concatenate(pending_imu) if pending_imu else None
        if imu is not None:
            pending_imu = [imu[imu["t"] >= horizon]] if np.any(imu["t"] >= horizon) else []
            imu = imu[imu["t"] < horizon]
        yield t, x, y, p, frames, imu, horizon
        if store is None:
            return


if __name__ == "__main__":
    serve(sys.argv[1], Connection(int(sys.argv[2])))
