"""WS /stream: frames pushed to the client, following the live head or sweeping a time range.

Three tasks per connection:

- the *receiver* reads subscriptions (msgpack or JSON), validates them and answers ``subscribed`` or
  ``error`` (the previous subscription stays in force after an error);
- the *producer* renders frames at the subscription's rate (live: whenever new events arrived, at
  most ``fps`` per second, and without a sensor at ``fps``, following the playback clock; sweep: t0,
  t0 + speed/fps, ... up to t1) and puts each in a slot of size one;
- the *sender* sends what is in the slot. The producer renders only while the sender is free: a tick
  that finds the previous frame still on its way renders nothing and is counted as dropped
  (``dropped`` in every frame, and the metrics). Nothing queues without bound however slow the client,
  and a client that stops reading costs no render.

A stream holds one of the ``max_streams`` slots only while a subscription is in force: with none for
``SUBSCRIBE_WAIT_S`` (from its start, or from a sweep's end) it is sent an error and closed (1008). A
client that stops reading stops answering the keepalive pings too, and its connection is dropped
(``server/connections.py``), which ends its session.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from collections import deque
from functools import partial

import numpy as np
from fastapi import APIRouter, WebSocket
from starlette.websockets import WebSocketDisconnect

from edmcgs import protocol
from edmcgs.errors import EdmcgsError, WindowUnavailable
from edmcgs.geometry import parse_pose
from edmcgs.server.errors import Busy, body_of
from edmcgs.server.service import Service, invalid

router = APIRouter()
log = logging.getLogger("edmcgs.server")

CLOSE_TRY_AGAIN_LATER = 1013
"""Close code when the stream limit (``max_streams``) is reached, after a ``busy`` error message."""
CLOSE_INTERNAL_ERROR = 1011
"""Close code when the stream itself failed, after an ``error`` message saying how."""
MIN_FPS = 0.01
"""Slowest frame rate a stream may ask for (a sweep's step is speed / fps)."""
CLOSE_POLICY = 1008
"""Close code when the stream went SUBSCRIBE_WAIT_S without a subscription (after an error saying so)."""
LIVE_IDLE_S = 0.5  # live mode re-checks its subscription at least this often while no events arrive
SUBSCRIBE_WAIT_S = 5.0
"""Longest a stream keeps its slot without a subscription in force."""
FAREWELL_S = 2.0
"""Longest the closing message and close of a session may take (a client may have stopped reading)."""


class LatestSlot:
    """Holds at most one item; ``put`` replaces an unsent one (and says so)."""

    def __init__(self):
        self._item = None

    @property
    def pending(self) -> bool:
        return self._item is not None

    def put(self, item) -> bool:
        """Store ``item``; True when it replaced one that was never taken (a dropped frame)."""
        replaced = self._item is not None
        self._item = item
        return replaced

    def take(self):
        item, self._item = self._item, None
        return item


class StreamSession:
    """One websocket connection (see the module docstring)."""

    def __init__(self, ws: WebSocket, service: Service):
        self.ws, self.service = ws, service
        self.sub: protocol.Subscription | None = None
        self.pose: np.ndarray | None = None
        self.size: tuple[int, int] = (0, 0)
        self.fps = 1.0
        self.restart = True  # the sweep starts over (a new subscription changed its timing)
        self.changed = asyncio.Event()
        self.frames = LatestSlot()
        self.control: deque[dict] = deque(maxlen=16)  # acks and errors; bounded like everything else
        self.wake = asyncio.Event()
        self.sender_free = asyncio.Event()  # no frame waits for the sender or is being sent
        self.sender_free.set()
        self.seq = 0
        self.dropped = 0
        self.failure: BaseException | None = None  # what ended the session, when not the client
        self.unsubscribed_since: float | None = asyncio.get_running_loop().time()  # None: subscribed
        self.expired = False  # ended for going SUBSCRIBE_WAIT_S without a subscription

    async def run(self) -> None:
        tasks = [asyncio.create_task(c) for c in (self._receive(), self._produce(), self._send(),
                                                  self._expire())]
        try:
            done, _ = await asyncio.wait(tasks, return_when=asyncio.FIRST_COMPLETED)
            for task in done:
                exc = task.exception()
                if exc is not None and not isinstance(exc, WebSocketDisconnect):
                    log.warning("websocket stream ended by %s: %s", type(exc).__name__, exc)
                    self.failure = exc
        finally:
            for task in tasks:
                task.cancel()
            await asyncio.gather(*tasks, return_exceptions=True)

    async def _expire(self) -> None:
        """Return (ending the session) once no subscription has been in force for SUBSCRIBE_WAIT_S."""
        loop = asyncio.get_running_loop()
        while True:
            since = self.unsubscribed_since
            left = SUBSCRIBE_WAIT_S if since is None else since + SUBSCRIBE_WAIT_S - loop.time()
            if left <= 0:
                self.expired = True
                return
            await asyncio.sleep(left)

    # ------------------------------------------------------------------ receiver
    async def _receive(self) -> None:
        while True:
            message = await self.ws.receive()
            if message["type"] == "websocket.disconnect":
                return
            raw = message.get("bytes") if message.get("bytes") is not None else message.get("text")
            try:
                self._apply(protocol.decode_message(raw))
            except (protocol.ProtocolError, EdmcgsError) as exc:
                self._control(body_of(exc))
            except Exception as exc:  # an input no check foresaw: still an answer, never a silent close
                log.warning("websocket message refused by %s: %s", type(exc).__name__, exc)
                self._control(protocol.ErrorBody(protocol.ErrorCode.INVALID_INPUT, "the message could not "
                                                 f"be applied ({type(exc).__name__})").to_message())
            else:
                self._control({"type": "subscribed", "subscription": self.sub.to_message()})

    def _apply(self, message: dict) -> None:
        """Validate a (partial) subscription against the protocol and the server's limits, then use it."""
        base = self.sub or protocol.Subscription()
        sub = base.updated(message)
        pose = None if sub.pose is None else parse_pose(sub.pose, name="pose")
        size = self.service.size(sub.width, sub.height)
        limit = self.service.settings.stream_max_fps
        if sub.fps < MIN_FPS:
            raise invalid("fps", f"fps={sub.fps:g} is below the minimum of {MIN_FPS:g}")
        if sub.fps > limit:
            raise invalid("fps", f"fps={sub.fps:g} exceeds the server's limit of {limit:g}")
        engine = self.service.engine
        for name in ("t0", "t1"):
            if getattr(sub, name) is not None and abs(getattr(sub, name)) > 1e9:
                raise invalid(name, f"{name} must be a number of seconds from the scene's start")
        timing = ("mode", "t0", "t1", "t0_us", "t1_us", "speed", "loop")
        if self.sub is None or any(getattr(sub, k) != getattr(self.sub, k) for k in timing):
            self.restart = True
        t0, t1 = self._sweep_range(sub)
        if sub.mode == "sweep" and t1 < t0:
            raise invalid("t1", f"the sweep ends ({engine.seconds_of(t1):.6f} s) before it starts "
                                f"({engine.seconds_of(t0):.6f} s)")
        self.sub, self.pose, self.size, self.fps = sub, pose, size, float(sub.fps)
        self.unsubscribed_since = None
        self.changed.set()

    def _sweep_range(self, sub: protocol.Subscription) -> tuple[int, int]:
        engine = self.service.engine
        t0 = sub.t0_us if sub.t0_us is not None else (
            engine.t_us_of_seconds(sub.t0) if sub.t0 is not None else engine.first_us)
        t1 = sub.t1_us if sub.t1_us is not None else (
            engine.t_us_of_seconds(sub.t1) if sub.t1 is not None else engine.end_us)
        return int(t0), int(t1)

    def _control(self, message: dict) -> None:
        self.control.append(message)
        self.wake.set()

    # ------------------------------------------------------------------ producer
    async def _produce(self) -> None:
        loop = asyncio.get_running_loop()
        engine = self.service.engine
        next_at = loop.time()
        sweep_t = 0
        last_window_end: int | None = None  # live: the stream time the previous frame reached
        last_serial: int | None = None  # live: the timebase (the model) the previous frame was rendered by
        while True:
            self.changed.clear()  # from here on, a new subscription wakes any wait below
            sub = self.sub
            if sub is None:
                await self.changed.wait()
                continue
            if sub.mode == "live":
                head = engine.head()
                # a frame when the head moves on, or when a newer model (a cold start's) is swapped in
                if head is None or (last_window_end is not None and head[0] <= last_window_end
                                    and engine.timebase.serial == last_serial):
                    await self._wait_for_events()
                    continue
                t_us = None
                last_serial = engine.timebase.serial
            else:
                t0, t1 = self._sweep_range(sub)
                if self.restart:
                    sweep_t, self.restart = t0, False
                if sweep_t > t1:
                    if not sub.loop:
                        self._control({"type": "end", "seq": self.seq})
                        self.sub, self.unsubscribed_since = None, loop.time()
                        continue
                    sweep_t = t0
                t_us = sweep_t
                sweep_t += max(1, round(1e6 * sub.speed / sub.fps))
            now = loop.time()
            if now < next_at:
                await asyncio.sleep(next_at - now)
            next_at = max(next_at + 1.0 / self.fps, loop.time())  # never a burst to catch up
            if self.changed.is_set():
                continue  # a new subscription while waiting: render what is asked now
            if not self.sender_free.is_set():  # the previous frame is on its way: a period at most
                await self._sender_free_or_changed(timeout=1.0 / self.fps)
                if self.changed.is_set():
                    continue
                if not self.sender_free.is_set():
                    # The client has not taken it: render nothing it cannot take (this tick's frame is
                    # dropped: its seq is skipped).
                    self.seq += 1
                    self._drop()
                    await self._sender_free_or_changed()
                    continue
            try:
                frame = await self.service.pool.run_stream(partial(
                    self.service.render_frame, t_us, self.pose, *self.size, sub.format, sub.render_mode))
            except WindowUnavailable as exc:
                if sub.mode == "live":
                    # The head is outside the trained span, or before this pass's first anchor: wait
                    # for it to move on rather than report every event batch.
                    head = engine.head()
                    last_window_end = None if head is None else head[0]
                else:
                    self._control(body_of(exc))
                continue
            except EdmcgsError as exc:
                self._control(body_of(exc))
                continue
            self.service.metrics.render.labels("stream").observe(frame.meta.render_ms / 1e3)
            window_start, window_end = frame.window
            message = frame.meta.to_message(frame.data)
            if sub.mode == "live":
                # Events new to this frame: those past the previous frame's window, or for the first
                # frame its whole window (not every batch the ring still remembers). The oldest of them
                # dates the frame: the batch that brought it, not merely one reaching past ``since``
                # (the previous frame's last batch does, by the microsecond its window left out).
                since = window_start if last_window_end is None else last_window_end
                oldest = self.service.ring.first_time(since, window_end)
                message["arrived_unix_us"] = None if oldest is None else \
                    self.service.arrivals.arrival_of(oldest)
                # The frame shows the stream as of window_end: known since the batch that reached it.
                message["head_arrived_unix_us"] = self.service.arrivals.arrival_of(window_end - 1)
                last_window_end = window_end
            self._push(message)

    async def _wait_for_events(self) -> None:
        """Until the ingest thread stores events (or a newer model is swapped in), the subscription
        changes, or LIVE_IDLE_S passes."""
        waiters = [asyncio.create_task(self.changed.wait()),
                   asyncio.create_task(self.service.signal.wait(LIVE_IDLE_S))]
        try:
            await asyncio.wait(waiters, return_when=asyncio.FIRST_COMPLETED)
        finally:
            for w in waiters:
                w.cancel()

    async def _sender_free_or_changed(self, timeout: float | None = None) -> None:
        waiters = [asyncio.create_task(self.changed.wait()), asyncio.create_task(self.sender_free.wait())]
        try:
            await asyncio.wait(waiters, timeout=timeout, return_when=asyncio.FIRST_COMPLETED)
        finally:
            for w in waiters:
                w.cancel()

    def _drop(self) -> None:
        self.dropped += 1
        self.service.metrics.frames_dropped.inc()

    def _push(self, frame: dict) -> None:
        frame["seq"] = self.seq
        self.seq += 1
        self.sender_free.clear()
        if self.frames.put(frame):
            self._drop()
        frame["dropped"] = self.dropped
        self.wake.set()

    # ------------------------------------------------------------------ sender
    async def _send(self) -> None:
        while True:
            await self.wake.wait()
            self.wake.clear()
            # The frame first: an "end" queued after a sweep's last frame must follow it.
            frame = self.frames.take()
            if frame is not None:
                await self.ws.send_bytes(protocol.pack(frame))
                self.service.metrics.frames_sent.inc()
            if not self.frames.pending:
                self.sender_free.set()
            while self.control:
                await self.ws.send_bytes(protocol.pack(self.control.popleft()))


@router.websocket("/stream")
async def stream(ws: WebSocket) -> None:
    """See the module docstring and ``edmcgs/protocol.py`` for the messages."""
    service: Service = ws.app.state.service
    await ws.accept()
    limit = service.settings.max_streams
    if service.metrics.stream_clients >= limit:
        service.metrics.streams_refused += 1
        busy = Busy(retry_after_s=1)
        message = body_of(busy) | {"detail": f"the server already serves {limit} streams (its limit); "
                                             "retry later"}
        with contextlib.suppress(RuntimeError, WebSocketDisconnect):
            await ws.send_bytes(protocol.pack(message))
            await ws.close(code=CLOSE_TRY_AGAIN_LATER, reason="too many streams")
        return
    service.metrics.stream_clients += 1
    t0 = time.perf_counter()
    session = StreamSession(ws, service)
    try:
        await session.run()
    finally:
        service.metrics.stream_clients -= 1
        # The client may be gone, or have stopped reading: a bounded farewell.
        with contextlib.suppress(Exception):
            async with asyncio.timeout(FAREWELL_S):
                await _farewell(ws, session)
        log.debug("stream closed after %.1f s", time.perf_counter() - t0)


async def _farewell(ws: WebSocket, session: StreamSession) -> None:
    """Close the stream, saying why when the server ends it."""
    if session.failure is not None:  # say why, then close with 1011 (internal error)
        body = protocol.ErrorBody(protocol.ErrorCode.RENDER_FAILED, "the stream failed: "
                                  f"{type(session.failure).__name__}: {session.failure}"[:300])
        await ws.send_bytes(protocol.pack(body.to_message()))
        await ws.close(code=CLOSE_INTERNAL_ERROR, reason="stream failed")
    elif session.expired:  # its slot goes to another viewer
        body = protocol.ErrorBody(protocol.ErrorCode.INVALID_INPUT,
                                  f"no subscription for {SUBSCRIBE_WAIT_S:g} s: the stream is closed (send "
                                  "one within that time of opening, or of a sweep's end)", "subscription")
        await ws.send_bytes(protocol.pack(body.to_message()))
        await ws.close(code=CLOSE_POLICY, reason="no subscription")
    else:
        await ws.close()
