"""The writer side of the ring buffer: a thread that reads a source into an EventRingBuffer and an
AnchorStore, and reconnects a camera that went away (the ring keeps what it had meanwhile).
"""

from __future__ import annotations

import threading
from collections.abc import Callable

from edmcgs.errors import DeviceDisconnected, EdmcgsError, SensorError
from edmcgs.sensor.buffer.anchors import AnchorStore
from edmcgs.sensor.buffer.ring import EventRingBuffer
from edmcgs.sensor.sources.base import EventSource, SensorBatch


class Ingest:
    """Pump ``source`` into ``ring`` (events; None: none kept) and ``anchors`` (frames) until the stream
    ends or stop().

    ``reconnect``: on DeviceDisconnected, call the source's ``reconnect()`` (exponential backoff) and
    go on; without it, or when reconnecting fails, the thread ends with ``error`` set.
    ``on_batch``: called with every batch after it is stored (e.g. metrics, recording).
    """

    def __init__(self, source: EventSource, ring: EventRingBuffer | None,
                 anchors: AnchorStore | None = None, *, reconnect: bool = True,
                 on_batch: Callable[[SensorBatch], None] | None = None) -> None:
        self.source, self.ring, self.anchors = source, ring, anchors
        self.reconnect = reconnect
        self.on_batch = on_batch
        self.batches = 0
        self.disconnects = 0
        self.finished = False
        self.error: BaseException | None = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def start(self) -> Ingest:
        self._thread = threading.Thread(target=self._run_guarded, name="edmcgs-ingest", daemon=True)
        self._thread.start()
        return self

    def stop(self, timeout: float | None = 5.0) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout)

    @property
    def running(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    def _run_guarded(self) -> None:
        # Any failure, of any type, ends the thread with ``error`` set: /healthz reports its reason
        # instead of a bare "stopped" (a corrupt timestamp raised OverflowError in the pacing).
        try:
            self.run()
        except EdmcgsError as exc:
            self.error = exc
        except Exception as exc:  # reported through error, not swallowed
            self.error = SensorError(f"the event source failed: {type(exc).__name__}: {exc}")
            self.error.__cause__ = exc

    def run(self) -> None:
        """The loop itself (runs in the caller's thread when called directly)."""
        while not self._stop.is_set():
            try:
                batch = self.source.read()
            except DeviceDisconnected:
                self.disconnects += 1
                if not self.reconnect or not hasattr(self.source, "reconnect"):
                    raise
                try:
                    self.source.reconnect(should_stop=self._stop.is_set)
                except EdmcgsError:
                    if self._stop.is_set():
                        return  # asked to stop while reconnecting: not an error
                    raise
                continue
            if batch is None:
                self.finished = True
                return
            if self.ring is not None:
                self.ring.push(batch.events, complete_until_us=batch.t_end_us)
            if self.anchors is not None and batch.frames is not None:
                self.anchors.add_frames(batch.frames)
            self.batches += 1
            if self.on_batch is not None:
                self.on_batch(batch)
