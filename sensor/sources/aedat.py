"""AEDAT4 replay: events, and frames and IMU when present, decoded in a child process.

dv-processing reads the file in ``edmcgs.sensor.sources.aedat_decoder``, a child process, because its decoder
can spin forever on a corrupt packet while holding the GIL. A child that sends nothing for ``stall_s``
seconds is killed and the replay fails with a ``ReplayFormatError`` naming the file; closing the
replay kills the child whatever it is doing. Trigger and other streams are skipped; a file of frames
alone (an APS recording) replays its frames with no events. Files are read forward packet by packet
(never whole). The child is a fresh interpreter running the decoder module itself (not a
``multiprocessing`` spawn, which re-imports the caller's ``__main__``), so a plain script without an
``if __name__ == "__main__":`` guard replays AEDAT4 too.
"""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import threading
from collections.abc import Iterator
from multiprocessing.connection import Connection
from pathlib import Path

import numpy as np

from edmcgs.errors import InvalidInputError, ReplayFormatError
from edmcgs.sensor.frames import Frames
from edmcgs.sensor.sources.base import StreamInfo
from edmcgs.sensor.sources.pacing import Pacing
from edmcgs.sensor.sources.replay import Chunk, Replay

_STARTUP_S = 60.0  # a fresh child's imports, on a loaded machine, before its hello


class AedatReplay(Replay):
    """Replay an .aedat4 file. ``pacing`` sets speed, start offset, looping and batch length;
    ``stall_s`` is how long the decoder may go silent before the file is declared unreadable."""

    def __init__(self, path: str | os.PathLike, pacing: Pacing | None = None, *, stall_s: float = 10.0,
                 **kwargs) -> None:
        super().__init__(pacing, **kwargs)
        self.path = Path(path)
        if not (isinstance(stall_s, int | float) and 0 < stall_s < float("inf")):
            raise InvalidInputError(f"stall_s must be a positive number of seconds, got {stall_s!r}")
        self.stall_s = float(stall_s)
        if not self.path.is_file():
            raise ReplayFormatError(f"{self.path}: no such file")
        self._lock = threading.Lock()
        self._process = self._conn = None
        self._busy = False  # the child is in the middle of a read
        info = self._exchange("open")[1]
        if "resolution" not in info:
            self.close()
            raise ReplayFormatError(f"{self.path}: no event or frame stream (streams: {info['streams']})")
        width, height = info["resolution"]
        self._info = StreamInfo(
            width=width, height=height, sensor=info["sensor"], has_frames=info["has_frames"],
            has_imu=info["has_imu"], live=False, t_range_us=info["t_range"], frame_size=info["frame_size"])

    def _start(self) -> None:
        self._kill()
        self._check_open()
        # A fresh interpreter (forking a process that runs torch and numba thread pools is not safe),
        # started on the decoder module: nothing of the caller's script runs in it.
        ours, theirs = socket.socketpair()
        conn, child_fd = Connection(ours.detach()), theirs.detach()
        try:
            process = subprocess.Popen([sys.executable, "-m", "edmcgs.sensor.sources.aedat_decoder",
                                        str(self.path), str(child_fd)], pass_fds=(child_fd,),
                                       stdin=subprocess.DEVNULL)
        except OSError as exc:
            conn.close()
            raise ReplayFormatError(f"{self.path}: cannot start the AEDAT4 decoder: {exc}") from exc
        finally:
            os.close(child_fd)
        with self._lock:
            self._process, self._conn = process, conn
        self._exchange("start the decoder", patience=_STARTUP_S)  # its hello

    def _exchange(self, doing: str, command: tuple | None = None, *, patience: float | None = None) -> tuple:
        """Send ``command`` (if any), then the child's next message within ``patience`` seconds (default
        ``stall_s``). A stall, a crash, a reported failure or a close from another thread is a
        ReplayFormatError."""
        if self._conn is None:
            self._start()
        conn, process = self._conn, self._process
        patience = self.stall_s if patience is None else patience
        try:
            if command is not None:
                conn.send(command)
            message = conn.recv() if conn.poll(patience) else ("stalled",)
        except (EOFError, OSError, AttributeError):  # the pipe closed (AttributeError: by close())
            message = ("closed",) if self.closed else ("crashed",)
        if message[0] not in ("hello", "info", "chunk", "end"):
            self._kill()
        if message[0] == "stalled":
            raise ReplayFormatError(f"{self.path}: the decoder stalled for {self.stall_s:g} s while trying "
                                    f"to {doing} (corrupt AEDAT4 file?)")
        if message[0] == "error":
            raise ReplayFormatError(f"{self.path}: cannot {message[1]} (not AEDAT4, truncated or corrupt?): "
                                    f"{message[2]}")
        if message[0] == "closed":
            raise ReplayFormatError(f"{self.path}: the replay was closed while trying to {doing}")
        if message[0] == "crashed":
            raise ReplayFormatError(f"{self.path}: the decoder died while trying to {doing} "
                                    f"(exit code {process.poll()})")
        return message

    def _chunks(self, begin_us: int) -> Iterator[Chunk]:
        if self._busy or self._conn is None:  # a read abandoned half-way: start afresh
            self._start()
            self._exchange("open")
        self._busy = True
        try:
            message = self._exchange("read the file", ("read", int(begin_us)))
            while message[0] == "chunk":
                t, x, y, p, frames, imu, horizon = message[1:]
                yield Chunk(events=self._validated(t, x, y, p), frames=_frames(frames), imu=imu,
                            horizon_us=horizon)
                message = self._exchange("read the file")
            self._busy = False
        finally:
            if self._busy:
                self._kill()

    def _kill(self) -> None:
        """Stop the child; safe from any thread (``close`` while the reader waits on the pipe)."""
        with self._lock:
            process, conn = self._process, self._conn
            self._process = self._conn = None
            self._busy = False
        if conn is not None:
            conn.close()
        if process is not None:
            process.kill()
            try:
                process.wait(5)
            except subprocess.TimeoutExpired:
                pass  # a zombie until the next wait: never block a close on it

    def close(self) -> None:
        super().close()
        self._kill()


def _frames(items: list[tuple[int, np.ndarray]]) -> Frames | None:
    if not items:
        return None
    return Frames([t for t, _ in items], np.stack([img for _, img in items]))
