"""One live source shared by a scene's render replicas.

A camera is opened by one process only. The scene's ingest deployment (``SceneIngest``, one replica)
owns it and keeps its latest batches in a bounded ring, each numbered; every render replica reads
them through ``RemoteSource``, an ``EventSource`` like any other, so its ``Ingest`` thread, ring,
anchors and online anchors are the single-process ones. A replica joins ``JOIN_BATCHES`` behind the
head, not at the ring's oldest batch: that one is the next to leave, so a reader starting there races
the eviction from its first pull. A replica that falls behind the shared ring loses the batches that
left it: it says so (a warning, ``missed_batches`` / ``missed_events``, the ``behind`` reason of
``edmcgs_events_dropped_total``) and goes on from the oldest batch still held.

If the ingest replica dies, Serve starts another, which opens the source again with a ring of its own
(a new ``epoch``). Each render replica's ``RemoteSource`` raises ``DeviceDisconnected`` when its pull
fails, and its ingest thread reconnects as it does for a camera (``reconnect``: back-off until the new
ingest answers, then on from its start); Serve's handle may also retry the pull on the new
replica by itself, which the ring's new epoch tells. What the old one held and had not handed over is
gone, and the replica logs and counts the reconnect.

``live: true`` with a ``replay`` in the Ray config plays the recording as a live camera through the
same path (a live scene tried without a camera): its batches carry no replay range, so each replica's
clock starts at its first event, as for a camera, and they are stamped with the wall clock as a
camera's are (the recording's first event at the moment the ingest replica opened it). So a replaced
ingest replica, which plays the recording again from its beginning, goes on after the old one's
events on every replica's clock, as a camera does after a reconnect; on the recording's own clock its
events would all fall behind the replicas' watermarks until it had played as long as the old one had.
"""

from __future__ import annotations

import asyncio
import itertools
import logging
import threading
import time
import uuid
from collections import deque
from dataclasses import replace

import numpy as np

from edmcgs.errors import DeviceDisconnected, SensorError
from edmcgs.sensor.events import Events, EventStats
from edmcgs.sensor.sources.base import Extras, SensorBatch, StreamInfo

log = logging.getLogger("edmcgs.server.ray")

RING_BATCHES = 2048
"""Batches the shared ring holds (at the default 5 ms per replay batch, about 10 s of stream)."""
PULL_WAIT_S = 1.0
"""Longest a pull waits for a new batch (the replica's ingest thread checks for stop between pulls)."""
JOIN_BATCHES = RING_BATCHES // 4
"""How far behind the head a new reader starts (about 2.5 s of stream: frames for its anchors, and
three quarters of the ring to spare before anything it has not read is evicted)."""
PULL_MAX = 256
"""Batches handed over per pull at most (about 1.3 s of stream: a reader that lags a round trip or
two catches up in one)."""
RECONNECT_S = 120.0
"""How long a render replica waits for a replaced ingest replica before its source is reported failed."""


class SharedRing:
    """The latest batches of a stream, numbered from 0, for any number of readers at their own pace.
    ``append``/``finish``/``fail`` from the reader thread; ``pull`` on ``loop`` (the replica's)."""

    def __init__(self, loop: asyncio.AbstractEventLoop | None = None, capacity: int = RING_BATCHES,
                 join: int = JOIN_BATCHES):
        if not 1 <= join <= capacity:
            raise ValueError(f"a reader joins 1 to capacity ({capacity}) batches behind the head, not {join}")
        self.ring: deque[tuple[int, int, SensorBatch]] = deque(maxlen=capacity)  # (seq, events before)
        self.join = join
        self.epoch = uuid.uuid4().hex  # this ring's identity: a replaced ingest replica has another
        self.next_seq = 0
        self.events = 0
        self.ended = False
        self.error: str | None = None
        self._lock = threading.Lock()
        self._loop = loop
        self._new = asyncio.Event()

    def _wake(self) -> None:
        if self._loop is not None:
            self._loop.call_soon_threadsafe(self._new.set)

    def append(self, batch: SensorBatch) -> None:
        with self._lock:
            self.ring.append((self.next_seq, self.events, batch))
            self.next_seq += 1
            self.events += len(batch.events)
        self._wake()

    def finish(self, error: str | None = None) -> None:
        self.ended, self.error = error is None, error
        self._wake()

    async def pull(self, after: int | None, wait_s: float = PULL_WAIT_S) -> dict:
        """The batches after ``after`` (None: a new reader, from ``join`` batches behind the head, or the
        oldest held), waiting up to ``wait_s`` for one.
        ``first_events``: events the stream held before the first batch returned (the caller's count
        of what it got tells what it missed); ``missed``: batches after ``after`` that left the ring;
        ``end``: no more will come; ``error``: the source's."""
        deadline = time.monotonic() + wait_s
        while True:
            self._new.clear()
            with self._lock:
                oldest = self.ring[0][0] if self.ring else self.next_seq
                start = max(self.next_seq - self.join if after is None else after + 1, oldest)
                skip = start - oldest  # seqs are consecutive: ``start`` sits at this index
                items = list(itertools.islice(self.ring, skip, skip + PULL_MAX))
                first_events = items[0][1] if items else self.events
            if items or self.ended or self.error is not None or time.monotonic() >= deadline:
                return {"batches": [b for _, _, b in items], "first_seq": start, "first_events": first_events,
                        "missed": 0 if after is None else start - (after + 1),
                        "end": self.ended and not items, "error": self.error, "epoch": self.epoch}
            try:
                await asyncio.wait_for(self._new.wait(), max(0.0, deadline - time.monotonic()))
            except TimeoutError:
                pass


class SceneIngest:
    """Serve deployment class (one replica per live scene): the source, its reader thread and the ring."""

    async def __init__(self, name: str, replay: str | None, loop: bool, batch_us: int):
        from edmcgs.sensor.sources.open import open_source
        from edmcgs.sensor.sources.pacing import Pacing

        self.name = name
        self.shared = SharedRing(asyncio.get_running_loop())  # the replica's loop: pull runs on it
        self._shift_us = 0
        if replay is not None:
            self.source = open_source(replay, pacing=Pacing(loop=loop, batch_us=batch_us))
            self._info = replace(self.source.info, live=True, t_range_us=None)
            self._shift_us = time.time_ns() // 1000 - self.source.info.t_range_us[0]
        else:
            self.source = open_source(live=True)
            self._info = self.source.info
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._read, name=f"edmcgs-ingest-{name}", daemon=True)
        self._thread.start()

    def _read(self) -> None:
        try:
            while not self._stop.is_set():
                batch = self.source.read()
                if batch is None:
                    break
                self.shared.append(batch.shifted(self._shift_us))
        except Exception as exc:  # reported to every replica's pull, and so on each one's /healthz
            log.error("scene %s: the shared source failed: %s: %s", self.name, type(exc).__name__, exc)
            self.shared.finish(f"{type(exc).__name__}: {exc}")
        else:
            self.shared.finish()

    def info(self) -> StreamInfo:
        return self._info

    def extras(self) -> Extras:
        """What the source states beside its streams, its trajectory on the replicas' clock."""
        extras = self.source.extras
        if extras.trajectory_t_us is None or not self._shift_us:
            return extras
        return replace(extras, trajectory_t_us=extras.trajectory_t_us + np.int64(self._shift_us))

    async def pull(self, after: int | None, wait_s: float = PULL_WAIT_S) -> dict:
        return await self.shared.pull(after, wait_s)

    def check_health(self) -> None:
        """Serve's probe: a failed source is reported to the replicas (their health), not restarted."""

    def __del__(self):
        stop = getattr(self, "_stop", None)
        if stop is not None:
            stop.set()
            self.source.close()


class RemoteSource:
    """An ``EventSource`` reading the scene's ``SceneIngest`` through its Serve handle (blocking calls:
    it runs in the replica's ingest thread)."""

    def __init__(self, handle, scene: str):
        self.handle, self.scene = handle, scene
        self._info: StreamInfo = handle.info.remote().result(timeout_s=60)
        self._extras: Extras = handle.extras.remote().result(timeout_s=60)
        self._stats = EventStats()
        self.after: int | None = None
        self.received_events = 0
        self.missed_batches = 0
        self.missed_events = 0
        self.pending: deque[SensorBatch] = deque()
        self.epoch: str | None = None
        self.reconnects = 0  # reading went on after the ingest replica failed (a new one, or it again)
        self._came_back = False

    @property
    def info(self) -> StreamInfo:
        return self._info

    @property
    def stats(self) -> EventStats:
        return self._stats

    @property
    def extras(self) -> Extras:
        return self._extras

    def read(self) -> SensorBatch | None:
        while not self.pending:
            try:
                answer = self.handle.pull.remote(self.after, PULL_WAIT_S).result(timeout_s=PULL_WAIT_S + 30)
            except Exception as exc:  # Ray's: the ingest replica died or cannot be reached
                raise DeviceDisconnected(f"scene {self.scene}: the shared source's ingest replica did not "
                                         f"answer ({type(exc).__name__}: {exc})") from exc
            if answer["error"] is not None:
                raise SensorError(f"the scene's shared source failed: {answer['error']}")
            if self.epoch is not None and answer["epoch"] != self.epoch:
                # a new ingest replica: its ring, and its numbers, start over
                log.warning("scene %s: the shared source restarted (a new ingest replica); joining it as "
                            "a new reader", self.scene)
                self.epoch, self.after, self.received_events = answer["epoch"], None, 0
                self.reconnects += 1
                self._came_back = False
                continue
            self.epoch = answer["epoch"]
            if self._came_back:  # the same ingest replica answers again after a failed pull
                self.reconnects += 1
                self._came_back = False
            batches = answer["batches"]
            if answer["missed"] > 0:
                missed_events = answer["first_events"] - self.received_events
                self.missed_batches += answer["missed"]
                self.missed_events += missed_events
                log.warning("scene %s: this replica fell behind the shared source and missed %d batches "
                            "(%d events)", self.scene, answer["missed"], missed_events)
            if batches:
                self.after = answer["first_seq"] + len(batches) - 1
                self.received_events = answer["first_events"] + sum(len(b.events) for b in batches)
                self.pending.extend(batches)
            elif answer["end"]:
                return None
            else:
                return SensorBatch(events=_no_events())  # nothing new yet: the ingest loop checks for stop
        return self.pending.popleft()

    def reconnect(self, *, budget_s: float = RECONNECT_S, initial_delay_s: float = 0.2,
                  max_delay_s: float = 5.0, should_stop=lambda: False) -> None:
        """Wait, backing off, until the scene's ingest deployment answers again (Serve replaces a dead
        replica); raise SensorError after ``budget_s``. ``Ingest`` calls this on DeviceDisconnected."""
        deadline = time.monotonic() + budget_s
        delay, last = float(initial_delay_s), None
        while not should_stop() and time.monotonic() < deadline:
            time.sleep(delay)
            try:
                self.handle.info.remote().result(timeout_s=max(1.0, min(30.0, deadline - time.monotonic())))
            except Exception as exc:
                last = exc
                delay = min(max_delay_s, delay * 2)
                continue
            self._came_back = True  # counted once the next pull says whether it is a new replica
            log.warning("scene %s: the shared source's ingest replica answers again", self.scene)
            return
        raise SensorError(f"scene {self.scene}: the shared source's ingest replica did not come back in "
                          f"{budget_s:.0f} s: {last}")

    def close(self) -> None:
        self.pending.clear()

    def __enter__(self) -> RemoteSource:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _no_events() -> Events:
    return Events.empty()
