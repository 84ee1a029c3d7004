"""Connections that never finish a request: a real uvicorn configured as ``edmcgs-serve`` configures it
(``connections.uvicorn_config``), serving the app around a stub service. Idle and half-sent connections
never count against ``max_connections`` and are closed after ``head_timeout_s``; requests in progress
are what is bounded."""

from __future__ import annotations

import asyncio
import socket
import threading
import time

import httpx
import pytest

from edmcgs.server.settings import Settings
from harness.server import free_port
from tests.support.stub import StubService

HEAD_TIMEOUT_S = 1.0


@pytest.fixture
def server():
    import uvicorn

    from edmcgs.server.app import create_app
    from edmcgs.server.connections import uvicorn_config

    settings = Settings(max_connections=8, head_timeout_s=HEAD_TIMEOUT_S, port=free_port())
    config = uvicorn_config(create_app(settings, service_factory=StubService), settings, log_level="warning")
    server = uvicorn.Server(config)
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    while not server.started:
        time.sleep(0.02)
    yield f"http://127.0.0.1:{settings.port}"
    server.should_exit = True
    thread.join(10)


def _open(url: str, count: int, send: bytes = b"") -> list[socket.socket]:
    host, port = url.removeprefix("http://").split(":")
    socks = []
    for _ in range(count):
        s = socket.create_connection((host, int(port)), timeout=10)
        if send:
            s.sendall(send)
        socks.append(s)
    return socks


def _closed_by_server(s: socket.socket) -> bytes | None:
    """What the server sent before closing ``s`` (None: still open after a while)."""
    s.settimeout(HEAD_TIMEOUT_S * 4)
    data = b""
    try:
        while chunk := s.recv(4096):
            data += chunk
    except TimeoutError:
        return None
    return data


def test_idle_and_half_sent_connections_leave_requests_served_and_are_closed(server):
    idle = _open(server, 40)
    half = _open(server, 40, b"GET /heal")
    slow = _open(server, 20, b"GET /healthz HTTP/1.1\r\nHost: 127.0.0.1\r\nX-Slow: ")
    try:
        with httpx.Client(base_url=server, timeout=5) as client:
            for _ in range(10):  # 100 connections open, max_connections 8: every request still served
                assert client.get("/healthz").status_code == 200
        for s in slow:  # a header a byte at a time keeps no connection past the deadline
            s.sendall(b"x")
        assert all(_closed_by_server(s) == b"" for s in idle), "silence gets closed, no answer"
        answers = {_closed_by_server(s).split(b"\r\n", 1)[0] for s in half + slow}
        assert answers == {b"HTTP/1.1 408 Request Timeout"}
    finally:
        for s in idle + half + slow:
            s.close()


def test_a_head_without_end_is_refused(server):
    (s,) = _open(server, 1, b"GET /healthz HTTP/1.1\r\nHost: 127.0.0.1\r\n")
    try:
        try:
            s.sendall(b"X-Pad: " + b"a" * 200_000 + b"\r\n")
            answer = _closed_by_server(s)
        except ConnectionResetError:  # closed with the rest unread: the kernel may reset before the 431
            answer = b"HTTP/1.1 431 (reset)"
        assert answer is not None and answer.startswith(b"HTTP/1.1 431 "), answer
    finally:
        s.close()


def test_a_kept_alive_connection_serves_its_next_requests(server):
    with httpx.Client(base_url=server, timeout=5) as client:
        for _ in range(3):
            assert client.get("/healthz").status_code == 200
            time.sleep(HEAD_TIMEOUT_S * 0.6)  # each wait alone under the deadline, all three over it


def test_requests_in_progress_beyond_the_limit_get_503_busy():
    from edmcgs.server.middleware import AccessMiddleware

    release = asyncio.Event()
    statuses = []

    async def slow_app(scope, receive, send):
        await release.wait()
        await send({"type": "http.response.start", "status": 200, "headers": []})
        await send({"type": "http.response.body", "body": b""})

    async def call(middleware):
        async def send(message):
            if message["type"] == "http.response.start":
                statuses.append(message["status"])

        async def receive():
            return {"type": "http.request", "body": b""}

        await middleware({"type": "http", "path": "/render", "headers": [(b"host", b"127.0.0.1")]},
                         receive, send)

    async def main():
        middleware = AccessMiddleware(slow_app, None, max_in_flight=2)
        calls = [asyncio.create_task(call(middleware)) for _ in range(3)]
        await asyncio.sleep(0.05)
        assert statuses == [503] and middleware.in_flight == 2
        release.set()
        await asyncio.gather(*calls)
        assert sorted(statuses) == [200, 200, 503] and middleware.in_flight == 0

    asyncio.run(main())
