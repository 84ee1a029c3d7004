"""Stream slots (``max_streams``) go back from clients that never subscribe or stop reading, and a client
that does not read costs no render: a real uvicorn as ``edmcgs-serve`` configures it, the app around a
stub service whose renders are counted; the hostile clients are raw sockets that read nothing."""

from __future__ import annotations

import base64
import contextlib
import json
import os
import socket
import struct
import threading
import time

import pytest
from websockets.exceptions import ConnectionClosed
from websockets.sync.client import connect

from edmcgs import protocol
from edmcgs.server import connections
from edmcgs.server.routes import stream
from edmcgs.server.settings import Settings
from harness.server import free_port
from tests.support.stub import StubService

SLOTS = 3
SWEEP = {"mode": "sweep", "fps": 60, "loop": True}


@pytest.fixture
def served(monkeypatch, request):
    """(port, service) of a server with SLOTS stream slots and short waits; ``request.param``: pings on."""
    import uvicorn

    from edmcgs.server.app import create_app

    monkeypatch.setattr(stream, "SUBSCRIBE_WAIT_S", 1.0)
    monkeypatch.setattr(connections, "PING_INTERVAL_S", 0.5 if getattr(request, "param", True) else None)
    monkeypatch.setattr(connections, "PING_TIMEOUT_S", 0.5)
    settings = Settings(max_streams=SLOTS, allowed_hosts=["*"], port=free_port())
    service = StubService(settings)
    service.frame_bytes = 1 << 20  # a client's socket buffers fill within a few frames
    config = connections.uvicorn_config(create_app(settings, service_factory=lambda _s: service), settings,
                                        log_level="warning")
    server = uvicorn.Server(config)
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    while not server.started:
        time.sleep(0.02)
    yield settings.port, service
    server.should_exit = True
    thread.join(10)


def _silent(port: int, subscription: dict | None = None) -> socket.socket:
    """A websocket that completes its handshake, sends ``subscription`` (if any), then reads nothing."""
    s = socket.create_connection(("127.0.0.1", port), timeout=10)
    key = base64.b64encode(os.urandom(16)).decode()
    s.sendall(f"GET /stream HTTP/1.1\r\nHost: 127.0.0.1\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
              f"Sec-WebSocket-Key: {key}\r\nSec-WebSocket-Version: 13\r\n\r\n".encode())
    head = b""
    while b"\r\n\r\n" not in head:
        head += s.recv(1)
    assert head.startswith(b"HTTP/1.1 101"), head
    if subscription is not None:
        payload, mask = json.dumps(subscription).encode(), os.urandom(4)
        masked = bytes(b ^ mask[i % 4] for i, b in enumerate(payload))
        s.sendall(bytes([0x81, 0x80 | len(payload)]) + mask + masked)
    return s


def _first_message(port: int) -> dict:
    """What a new viewer is told first: ``subscribed``, or ``busy`` while every slot is held."""
    with contextlib.suppress(ConnectionClosed), connect(f"ws://127.0.0.1:{port}/stream", max_size=None,
                                                        open_timeout=10) as ws:
        with contextlib.suppress(ConnectionClosed):  # a busy server may close before it reads
            ws.send(json.dumps(SWEEP))
        return protocol.unpack(ws.recv(timeout=10))
    raise AssertionError("closed without a message")


def _until(condition, timeout: float = 60.0) -> float:
    """Until ``condition()``; ``timeout`` bounds a hang, not a speed (the slots' timing is in bench.hostile:
    a loaded machine may take seconds for a first render)."""
    t0 = time.monotonic()
    while not condition():
        assert time.monotonic() - t0 < timeout, "not within the time"
        time.sleep(0.05)
    return time.monotonic() - t0


@pytest.mark.parametrize("served", [False], indirect=True, ids=["no pings"])  # the subscription's wait alone
def test_streams_that_never_subscribe_give_their_slots_back(served):
    port, service = served
    silent = [_silent(port) for _ in range(SLOTS)]
    try:
        busy = _first_message(port)
        assert busy["type"] == "error" and busy["error"] == "busy"
        _until(lambda: service.metrics.stream_clients == 0)
        close = b"\x88" + bytes([2 + len(b"no subscription")]) + struct.pack("!H", 1008) + b"no subscription"
        for s in silent:  # told why, then closed with 1008
            s.settimeout(5)
            data = b""
            while close not in data:
                data += s.recv(65536)
            assert b"no subscription for 1 s" in data.split(close)[0]
        assert _first_message(port)["type"] == "subscribed"
    finally:
        for s in silent:
            s.close()


def test_streams_that_stop_reading_give_their_slots_back_and_cost_no_renders(served):
    port, service = served
    silent = [_silent(port, SWEEP) for _ in range(SLOTS)]
    try:
        _until(lambda: getattr(service, "renders", 0) > 0)
        _until(lambda: service.metrics.stream_clients == 0)
        renders = service.renders
        time.sleep(1.0)
        assert service.renders == renders, "renders for clients already gone"
        assert renders < 20 * SLOTS, f"{renders} renders for clients that read nothing"
        assert _first_message(port)["type"] == "subscribed"
    finally:
        for s in silent:
            s.close()


@pytest.mark.parametrize("served", [False], indirect=True, ids=["no pings"])
def test_a_client_that_does_not_read_is_not_rendered_for(served):
    port, service = served
    s = _silent(port, SWEEP)
    try:
        _until(lambda: getattr(service, "renders", 0) > 0)
        time.sleep(2.0)  # its socket buffers fill; the sender waits
        renders = service.renders
        time.sleep(2.0)  # at 60 fps: 120 renders if it were rendered for
        assert service.renders - renders <= 1, service.renders - renders
        assert service.metrics.stream_clients == 1
    finally:
        s.close()
