"""Connections as ``edmcgs-serve`` serves them: HTTP requests must say what they want (a deadline and a
size for each request's head), websocket peers must keep reading.

uvicorn closes a connection idle *between* requests (``timeout_keep_alive``), but arms nothing before a
connection's first request, cancels even that timer on any byte, and its httptools parser keeps header
bytes without a bound. A client that connects and sends nothing, or half a request line, or one header
byte a second, would hold its connection (and a file descriptor) for as long as it likes; one that sends
headers without end grows the server's memory. uvicorn has no setting for either, so its httptools
protocol is subclassed here: the request line and headers must arrive within ``head_timeout_s`` of the
connection opening (or of the request's first byte, for later requests on a kept-alive connection) and
within ``MAX_HEAD_BYTES``; otherwise the connection is answered 408 or 431 (when it sent anything) and
closed. Such connections never count against ``max_connections`` either: the app counts requests in
progress (``middleware.AccessMiddleware``), not connections.
"""

from __future__ import annotations

import asyncio
import socket

from uvicorn.protocols.http.httptools_impl import HttpToolsProtocol
from uvicorn.protocols.websockets.websockets_sansio_impl import WebSocketsSansIOProtocol

MAX_HEAD_BYTES = 64 * 1024
"""Largest request head (request line and headers) a connection may send; uvicorn's h11 allows 16 KiB."""


class HeadDeadlineProtocol(HttpToolsProtocol):
    """uvicorn's httptools protocol with the deadline and size of a request head (module docstring)."""

    head_timeout_s = 10.0

    def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]
        super().connection_made(transport)
        self._head_bytes = 0
        self._head_timer: asyncio.TimerHandle | None = None
        self._arm()

    def on_message_begin(self) -> None:
        super().on_message_begin()
        self._head_bytes = 0
        if self._head_timer is None:  # a later request on a kept-alive connection: from its first byte
            self._arm()

    def on_headers_complete(self) -> None:
        self._disarm()
        super().on_headers_complete()

    def data_received(self, data: bytes) -> None:
        super().data_received(data)
        if self._head_timer is not None and not self.transport.is_closing():
            self._head_bytes += len(data)
            if self._head_bytes > MAX_HEAD_BYTES:
                self._refuse(431, "Request Header Fields Too Large")

    def connection_lost(self, exc: Exception | None) -> None:
        self._disarm()
        super().connection_lost(exc)

    def _arm(self) -> None:
        self._head_timer = self.loop.call_later(self.head_timeout_s, self._late)

    def _disarm(self) -> None:
        if self._head_timer is not None:
            self._head_timer.cancel()
            self._head_timer = None

    def _late(self) -> None:
        self._head_timer = None
        if self.transport.is_closing():
            return
        if self.cycle is not None and not self.cycle.response_complete:
            self._arm()  # a pipelined head while the previous response is still being made: wait for it
            return
        self._refuse(408, "Request Timeout")

    def _refuse(self, status: int, phrase: str) -> None:
        """Answer ``status`` (to a client that sent part of a request; silence gets none) and close."""
        self._disarm()
        if self._head_bytes:
            body = f"{phrase}: the request line and headers must come within {self.head_timeout_s:g} s " \
                   f"and {MAX_HEAD_BYTES // 1024} KiB\n"
            self.transport.write(f"HTTP/1.1 {status} {phrase}\r\ncontent-type: text/plain; charset=utf-8\r\n"
                                 f"content-length: {len(body)}\r\nconnection: close\r\n\r\n{body}".encode())
        self.transport.close()


def head_deadline_protocol(head_timeout_s: float) -> type[HeadDeadlineProtocol]:
    """The protocol class to give uvicorn (``uvicorn.Config(http=...)``) for this deadline."""
    return type("HeadDeadlineProtocol", (HeadDeadlineProtocol,), {"head_timeout_s": float(head_timeout_s)})


class DroppingWebSocketProtocol(WebSocketsSansIOProtocol):
    """uvicorn's websocket protocol, except that a peer which stops reading is dropped, and that the app
    learns of a connection the protocol ended as of a disconnect.

    A peer that stops reading answers no keepalive ping. uvicorn then writes a close frame and closes
    the transport gracefully, which waits for the unsent frames to drain (for a peer that reads nothing
    they never do), and tells the app nothing: its next send waits forever for the transport to take
    more, and the stream keeps its slot. Here the transport is aborted instead: the connection ends at
    once, the app's receive sees a disconnect and a waiting send fails. A transport still open
    CLOSE_GRACE_S after the app ended (a close the peer never reads) is aborted too. The socket's send
    buffer is WS_SEND_BUFFER, so a ping waits behind little and a slow reader answers it in time.

    When the protocol itself closes the connection (a ping unanswered; a message over ``ws_max_size``,
    compressed or not, closed with 1009), uvicorn fails the app's next send with a RuntimeError ("after
    sending 'websocket.close'"), which reads as the app's own failure; here it is a disconnect.
    """

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        self._lost = False
        super().connection_made(transport)
        sock = transport.get_extra_info("socket")
        if sock is not None:  # frames queue in the app's slot, not by megabytes in the kernel
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, WS_SEND_BUFFER)

    def connection_lost(self, exc: Exception | None) -> None:
        self._lost = True
        super().connection_lost(exc)

    def keepalive_timeout(self) -> None:
        super().keepalive_timeout()
        self.disconnected = True
        self._abort_if_open()

    def handle_parser_exception(self) -> None:
        super().handle_parser_exception()
        self.disconnected = True

    async def run_asgi(self) -> None:
        await super().run_asgi()
        self.loop.call_later(CLOSE_GRACE_S, self._abort_if_open)

    def _abort_if_open(self) -> None:
        if not self._lost:
            self.transport.abort()


WS_MAX_BYTES = 1 << 20
"""Largest websocket message a client may send (after decompression); a larger one closes with 1009."""
PING_INTERVAL_S = 2.0
PING_TIMEOUT_S = 5.0
"""Keepalive pings: a peer that leaves one unanswered this long is dropped (within 7 s of its last pong).
A ping waits behind the frames already queued to the peer: a slow reader still answers in time."""
WS_SEND_BUFFER = 256 * 1024
"""A websocket's kernel send buffer (Linux doubles it): what waits there ahead of a frame or a ping is
at most about half a MiB, however slow the peer; the kernel's own sizing queued megabytes on loopback,
seconds of stale frames for a slow reader, ahead of the ping it must answer in PING_TIMEOUT_S."""
CLOSE_GRACE_S = 15.0
"""How long a websocket whose app has ended may take to close before it is aborted."""


def uvicorn_config(app, settings, *, log_level: str = "info", **options):
    """The uvicorn configuration ``edmcgs-serve`` runs ``app`` with: this module's protocols (the
    settings' head deadline; websocket peers that stop reading dropped), websocket messages up to
    WS_MAX_BYTES, and no connection limit of uvicorn's (it counts idle connections; the app bounds
    requests in progress instead)."""
    import uvicorn

    return uvicorn.Config(app, host=settings.host, port=settings.port, log_level=log_level,
                          http=head_deadline_protocol(settings.head_timeout_s), ws=DroppingWebSocketProtocol,
                          ws_max_size=WS_MAX_BYTES, ws_ping_interval=PING_INTERVAL_S,
                          ws_ping_timeout=PING_TIMEOUT_S, timeout_graceful_shutdown=3, **options)


def raise_fd_limit() -> int:
    """Raise this process's soft limit of open files to its hard limit (each connection is one); returns
    the soft limit now in force."""
    import resource

    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    want = hard if hard != resource.RLIM_INFINITY else max(soft, 1 << 16)
    if soft != resource.RLIM_INFINITY and soft < want:
        try:
            resource.setrlimit(resource.RLIMIT_NOFILE, (want, hard))
            soft = want
        except (ValueError, OSError):  # a container may forbid it: serve with what there is
            pass
    return soft
