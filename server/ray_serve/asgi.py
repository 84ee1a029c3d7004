"""Driving an ASGI app in-process: one HTTP request, or one websocket session fed by a queue.

A scene replica runs the single-process service's app (``create_app``) and answers the gateway's calls
through it, so the routes, their validation and their error bodies are the very ones of
``edmcgs-serve``. Plain asyncio; nothing here knows Ray.
"""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import AsyncIterator
from dataclasses import dataclass, field

HOP_BY_HOP = frozenset({"connection", "keep-alive", "transfer-encoding", "upgrade", "content-length",
                        "te", "trailer", "proxy-connection", "sec-websocket-key",
                        "sec-websocket-version", "sec-websocket-extensions"})
"""Headers that belong to one connection, never forwarded."""


@dataclass
class HttpResult:
    """A response as plain data (it crosses process boundaries)."""

    status: int
    headers: list[tuple[str, str]]
    body: bytes


def forwarded(headers: list[tuple[str, str]]) -> list[tuple[bytes, bytes]]:
    """ASGI headers of a forwarded request: lowercase names, hop-by-hop ones left out."""
    return [(k.lower().encode("latin-1"), v.encode("latin-1")) for k, v in headers
            if k.lower() not in HOP_BY_HOP]


def _scope(kind: str, path: str, query: str, headers: list[tuple[str, str]], client: str,
           root_path: str = "") -> dict:
    # ``root_path``: where the client sees the app (the pages that link to the app's own URLs use it);
    # as ASGI says, ``path`` includes it.
    full = root_path + path
    return {"type": kind, "asgi": {"version": "3.0"}, "http_version": "1.1", "scheme":
            "http" if kind == "http" else "ws", "path": full, "raw_path": full.encode(),
            "root_path": root_path,
            "query_string": query.encode("latin-1"), "headers": forwarded(headers),
            "client": (client, 0), "server": ("127.0.0.1", 80), "subprotocols": [], "extensions": {}}


async def http_request(app, method: str, path: str, query: str, headers: list[tuple[str, str]],
                       client: str = "127.0.0.1", root_path: str = "") -> HttpResult:
    """One request through ``app``; the whole body is collected."""
    scope = _scope("http", path, query, headers, client, root_path)
    scope["method"] = method.upper()
    sent_request = False
    done = asyncio.Event()
    status, out_headers, body = 500, [], bytearray()

    async def receive() -> dict:
        nonlocal sent_request
        if not sent_request:
            sent_request = True
            return {"type": "http.request", "body": b"", "more_body": False}
        await done.wait()
        return {"type": "http.disconnect"}

    async def send(message: dict) -> None:
        nonlocal status, out_headers
        if message["type"] == "http.response.start":
            status = message["status"]
            out_headers = [(k.decode("latin-1"), v.decode("latin-1")) for k, v in message.get("headers", [])]
        elif message["type"] == "http.response.body":
            body.extend(message.get("body", b""))
            if not message.get("more_body", False):
                done.set()

    try:
        await app(scope, receive, send)
    finally:
        done.set()
    headers_out = [(k, v) for k, v in out_headers if k.lower() not in HOP_BY_HOP]
    return HttpResult(status, headers_out, bytes(body))


@dataclass
class WsMessage:
    """One message the app sent: ``bytes`` or ``text``; ``close`` set on the closing one."""

    bytes: bytes | None = None
    text: str | None = None
    close: int | None = None
    reason: str = ""


@dataclass
class WebSocketSession:
    """A websocket connection to ``app`` held in-process: ``send`` feeds it client messages,
    ``messages()`` yields what it sends until it closes or ``close()`` is called."""

    app: object
    path: str
    query: str
    headers: list[tuple[str, str]]
    client: str = "127.0.0.1"
    _inbox: asyncio.Queue = field(default_factory=asyncio.Queue)
    _outbox: asyncio.Queue = field(default_factory=asyncio.Queue)
    _task: asyncio.Task | None = None
    accepted: bool = False

    def start(self) -> WebSocketSession:
        self._inbox.put_nowait({"type": "websocket.connect"})
        self._task = asyncio.create_task(self._run())
        return self

    async def _run(self) -> None:
        scope = _scope("websocket", self.path, self.query, self.headers, self.client)
        try:
            await self.app(scope, self._inbox.get, self._send)
        except Exception as exc:  # the app failed outside its own handlers: the session closes
            await self._outbox.put(WsMessage(close=1011, reason=f"{type(exc).__name__}: {exc}"))
        finally:
            await self._outbox.put(None)

    async def _send(self, message: dict) -> None:
        kind = message["type"]
        if kind == "websocket.accept":
            self.accepted = True
        elif kind == "websocket.send":
            await self._outbox.put(WsMessage(bytes=message.get("bytes"), text=message.get("text")))
        elif kind == "websocket.close":
            await self._outbox.put(WsMessage(close=message.get("code", 1000), reason=message.get("reason")
                                             or ""))
        elif kind == "websocket.http.response.start":
            await self._outbox.put(WsMessage(close=1008, reason=f"refused ({message.get('status')})"))

    def send(self, data: bytes | str) -> None:
        """A client message."""
        key = "bytes" if isinstance(data, bytes) else "text"
        self._inbox.put_nowait({"type": "websocket.receive", key: data})

    async def messages(self) -> AsyncIterator[WsMessage]:
        """What the app sends, up to and including its close (or the end of the app)."""
        while True:
            item = await self._outbox.get()
            if item is None:
                return
            yield item
            if item.close is not None:
                return

    def disconnect(self, code: int = 1000) -> None:
        """The client went away: the app sees a disconnect (``messages()`` ends once the app does)."""
        self._inbox.put_nowait({"type": "websocket.disconnect", "code": code})

    async def close(self, code: int = 1000) -> None:
        """The client went away: the app sees a disconnect; wait for it briefly, then cancel it."""
        self._inbox.put_nowait({"type": "websocket.disconnect", "code": code})
        if self._task is not None and not self._task.done():
            try:
                await asyncio.wait_for(asyncio.shield(self._task), timeout=2.0)
            except (TimeoutError, asyncio.CancelledError):
                self._task.cancel()
                with contextlib.suppress(BaseException):
                    await self._task
