"""A client's websocket relayed to a scene's replicas.

One replica-side session (``SceneReplica.stream``, a streaming call) lives as long as the connection:
the client's later messages reach it through the gateway's mailbox (``mailbox.py``), so a running
sweep keeps its position when the viewer sends a new pose. The client's newest messages are also kept
(``History``), and when the replica dies the session is started again on a live one from them (its
``seq`` starts over); the replies to messages already answered are not sent twice.

Every hop is bounded in bytes: a client message over ``WS_MAX_BYTES`` closes the connection with 1009
(Serve's proxy takes up to 16 MiB, the single process 1 MiB); one longer than any subscription
(``protocol.MAX_MESSAGE_BYTES``) is answered here with the scene's error and goes no further, so what
crosses Ray to the mailbox and the replica stays small; the messages read but not yet handed to the
mailbox are at most ``INBOX_BYTES`` (past that, 1008: the client sends faster than the scene takes
them), the mailbox holds at most its ``MAX_PENDING_BYTES`` per session, and the history
``HISTORY_BYTES``.
"""

import asyncio
import contextlib
import logging
import time
import uuid
from collections import deque

from fastapi import WebSocket
from starlette.websockets import WebSocketDisconnect

from edmcgs import protocol
from edmcgs.server.connections import WS_MAX_BYTES
from edmcgs.server.errors import body_of
from edmcgs.server.ray_serve.asgi import WsMessage
from edmcgs.server.ray_serve.retry import Retrier, retryable

log = logging.getLogger("edmcgs.server.ray")

MAX_HISTORY = 256
"""Client messages a relayed stream keeps to replay (each a partial subscription, applied in order)."""
HISTORY_BYTES = 256 * 1024
"""Their bytes at most (the newest message is always kept)."""
INBOX_BYTES = 4 << 20
"""Bytes of client messages read and not yet in the mailbox before the connection is closed (1008)."""
CLOSE_TOO_BIG = 1009
TOO_FAST = WsMessage(close=1008, reason="the client sends faster than the scene takes its messages")


class History:
    """The client's newest messages, at most MAX_HISTORY and HISTORY_BYTES of them, and the count of all
    it ever sent: a restarted session replays them, and skips the replies the client already had."""

    def __init__(self, max_messages: int = MAX_HISTORY, max_bytes: int = HISTORY_BYTES):
        self.max_messages, self.max_bytes = max_messages, max_bytes
        self.messages: deque[bytes | str] = deque()
        self.bytes = 0
        self.sent = 0

    def add(self, data: bytes | str) -> None:
        self.messages.append(data)
        self.bytes += len(data)
        self.sent += 1
        while len(self.messages) > 1 and (len(self.messages) > self.max_messages
                                          or self.bytes > self.max_bytes):
            self.bytes -= len(self.messages.popleft())

    def answered(self, replies: int) -> int:
        """Of the messages kept, how many the client has had its reply to (``replies`` of all it sent,
        answered in order)."""
        return max(0, replies - (self.sent - len(self.messages)))
CONTROL = ("subscribed", "error")
"""The replies a stream sends, one per client message (frames and ``end`` are not replies)."""


class StreamRelay:
    """One client's websocket relayed to a scene (see the module docstring)."""

    def __init__(self, ws: WebSocket, handle, retrier: Retrier, client: str, mailbox):
        self.ws, self.handle, self.retrier, self.client = ws, handle, retrier, client
        self.mailbox = mailbox
        self.history = History()
        self.replies = 0  # control replies (subscribed / error) the client has had, one per message
        self.inbox: asyncio.Queue = asyncio.Queue()
        self.inbox_bytes = 0
        self.delivered = False  # a message reached the client since the last look
        self.session: str | None = None  # the running replica-side session's id in the mailbox
        self.query = ws.url.query
        self.headers = list(ws.headers.items())

    async def _read(self) -> None:
        """Client messages into the inbox, bounded; a refusal goes into it as the close to send."""
        try:
            while True:
                message = await self.ws.receive()
                if message["type"] == "websocket.disconnect":
                    break
                data = message.get("bytes") if message.get("bytes") is not None else message.get("text")
                if data is None:
                    continue
                if len(data) > WS_MAX_BYTES:
                    await self.inbox.put(WsMessage(close=CLOSE_TOO_BIG, reason=f"a message of {len(data)} "
                                                   f"bytes; at most {WS_MAX_BYTES}"))
                    break
                if len(data) > protocol.MAX_MESSAGE_BYTES:  # never a subscription: the scene's answer,
                    await self._refuse(data)               # given here, so it never crosses Ray
                    continue
                if self.inbox_bytes + len(data) > INBOX_BYTES:
                    await self.inbox.put(TOO_FAST)
                    break
                self.inbox_bytes += len(data)
                await self.inbox.put(data)
        finally:
            await self.inbox.put(None)

    async def _refuse(self, data: bytes | str) -> None:
        """Answer a message longer than any subscription with the error the scene's session would."""
        try:
            protocol.decode_message(data)
        except protocol.ProtocolError as exc:
            await self.ws.send_bytes(protocol.pack(body_of(exc)))

    async def _start(self) -> asyncio.Task:
        """A new replica-side session fed every message so far; later ones go through the mailbox."""
        await self._end_session()
        self.session = uuid.uuid4().hex
        await self.mailbox.open.remote(self.session)
        return asyncio.create_task(self._pump(list(self.history.messages), self.session))

    async def _end_session(self) -> None:
        session, self.session = self.session, None
        if session is not None:
            with contextlib.suppress(Exception):
                await self.mailbox.close.remote(session)

    async def _pump(self, history: list, session: str) -> WsMessage | None:
        """One replica-side session: forward what it sends; return its close (None: it just ended)."""
        skip = self.history.answered(self.replies)
        gen = self.handle.options(stream=True).stream.remote("/stream", self.query, self.headers,
                                                             history, self.client, self.mailbox, session)
        try:
            async for item in gen:
                if item.close is not None:
                    return item
                if skip and item.bytes is not None:
                    kind = protocol.unpack(item.bytes).get("type")
                    if kind in CONTROL:
                        skip -= 1
                        continue  # the reply to a replayed message: the client had it already
                await self._send(item)
        finally:
            gen.cancel()
        return None

    async def _send(self, item: WsMessage) -> None:
        self.delivered = True
        if item.bytes is not None:
            if len(item.bytes) < 4096 and protocol.unpack(item.bytes).get("type") in CONTROL:
                self.replies += 1
            await self.ws.send_bytes(item.bytes)
        elif item.text is not None:
            await self.ws.send_text(item.text)

    async def run(self) -> None:
        reader = asyncio.create_task(self._read())
        pump: asyncio.Task | None = None
        failing_since: float | None = None  # replicas dying since then, none answering
        try:
            while True:
                if pump is None:
                    pump = await self._start()
                getter = asyncio.create_task(self.inbox.get())
                done, _ = await asyncio.wait({pump, getter}, return_when=asyncio.FIRST_COMPLETED)
                if getter in done:
                    data = getter.result()
                    if data is None:  # the client went away
                        return
                    if isinstance(data, WsMessage):  # refused by the reader
                        await self._close(data)
                        return
                    self.inbox_bytes -= len(data)
                    self.history.add(data)
                    if not await self.mailbox.put.remote(self.session, data) and not pump.done():
                        await self._close(TOO_FAST)
                        return
                    continue  # a session that ended meanwhile is handled below, history and all
                getter.cancel()
                exc = pump.exception()
                if self.delivered:
                    failing_since, self.delivered = None, False
                if exc is None:
                    closing = pump.result()
                    await self._close(closing or WsMessage(close=1000))
                    return
                if not retryable(exc):
                    raise exc
                if failing_since is None:
                    failing_since = time.monotonic()
                elif time.monotonic() - failing_since > self.retrier.retry_for_s:
                    await self._close(WsMessage(close=1011, reason="no replica of the scene answers"))
                    return
                self.retrier.retries += 1
                self.retrier.stream_restarts += 1
                log.warning("stream: its replica died (%s); restarting the session", type(exc).__name__)
                await asyncio.sleep(0.05)
                pump = None
        except WebSocketDisconnect:
            return
        finally:
            reader.cancel()
            if pump is not None and not pump.done():
                pump.cancel()
                with contextlib.suppress(BaseException):
                    await pump
            await self._end_session()

    async def _close(self, item: WsMessage) -> None:
        with contextlib.suppress(Exception):
            await self.ws.close(code=item.close or 1000, reason=item.reason)
