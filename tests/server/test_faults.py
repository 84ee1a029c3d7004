"""Hostile input and faults, one test each (unit level: no server process unless stated)."""

from __future__ import annotations

import functools
import types

import msgpack
import numpy as np
import pytest

from edmcgs.errors import EdmcgsError, ReplayFormatError
from edmcgs.sensor.buffer.ingest import Ingest
from edmcgs.sensor.buffer.ring import EventRingBuffer
from edmcgs.sensor.sources.pacing import Pacer
from edmcgs.server.service import Service
from edmcgs.server.settings import LOOPBACK
from tests.support.stub import StubService


class _Failing:
    """A source whose read raises an arbitrary (non-edmcgs) exception."""

    def __init__(self, exc: BaseException):
        self.exc = exc

    def read(self):
        raise self.exc


def _health_of(ingest: Ingest) -> dict:
    stub = types.SimpleNamespace(ingest=ingest, source=object(), ring=EventRingBuffer(4), learning=None,
                                 engine=types.SimpleNamespace(head=lambda: None),
                                 settings=types.SimpleNamespace(device="cpu"), started_unix=0.0)
    return Service.health(stub)[1]


@pytest.mark.parametrize("exc", [OverflowError("timestamp too large to convert to C _PyTime_t"),
                                 ValueError("boom"), ZeroDivisionError("x")])
def test_any_ingest_exception_reaches_healthz(exc):
    ingest = Ingest(_Failing(exc), EventRingBuffer(16), reconnect=False).start()
    ingest.stop(timeout=5)
    assert isinstance(ingest.error, EdmcgsError)
    details = _health_of(ingest)
    assert details["source"] == "error"
    assert type(exc).__name__ in details["source_error"] and str(exc) in details["source_error"]


def test_corrupt_timestamp_is_a_clear_pacing_error():
    now = [0.0]
    pacer = Pacer(1.0, clock=lambda: now[0], sleep=lambda s: None)
    pacer.wait_until(1_600_000_000_000_000)
    with pytest.raises(ReplayFormatError, match="corrupt timestamp"):
        pacer.wait_until(np.iinfo(np.int64).max)


@pytest.mark.parametrize("kwargs", [{"device": "banana"}, {"device": "cuda:99"}, {"ring_events": 10**12},
                                    {"max_width": 10**9}, {"render_queue": 10**9}, {"speed": float("inf")},
                                    {"stream_max_fps": 1e9}, {"max_streams": -1}])
def test_settings_refuse_missing_devices_and_huge_rings(kwargs):
    from pydantic import ValidationError

    from edmcgs.server.settings import Settings

    with pytest.raises(ValidationError) as info:
        Settings(**kwargs)
    assert any(w in str(info.value) for w in ("available", "memory", "unknown torch device", "less than",
                                              "greater than"))


def test_serve_cli_says_one_line(capsys):
    from edmcgs.server.cli import main

    assert main(["--device", "banana"]) == 2
    err = capsys.readouterr().err
    assert "device" in err and "Traceback" not in err


# ----------------------------------------------------------------------------- an app around a stub


@pytest.fixture
def stub_client():
    from fastapi.testclient import TestClient

    from edmcgs.server.app import create_app
    from edmcgs.server.settings import Settings

    # The loopback allowlist, plus the name TestClient's websockets always send as their Host.
    app = create_app(Settings(allowed_hosts=[*LOOPBACK, "testserver"]), service_factory=StubService)
    with TestClient(app, base_url="http://127.0.0.1:8000") as client:
        yield client


@pytest.mark.parametrize("pose", ["[" * 1500, "[" * 1500 + "]" * 1500, "1," * 5000, "[[[1]]]"])
def test_deep_or_huge_pose_is_a_422_naming_pose(stub_client, pose):
    response = stub_client.get("/render", params={"pose": pose})
    assert response.status_code == 422
    assert response.json()["param"] == "pose"


def test_a_looping_replay_never_overflows_and_keeps_the_span_renderable():
    from edmcgs.sensor.events import Events
    from edmcgs.server.live import clock
    from edmcgs.server.service import retain_passes

    period, per_pass, t0 = 2_000_000, 30_000, 1_600_000_000_000_000
    ring = EventRingBuffer(4 * per_pass)  # room for 4 passes: a loop used to fill it, then overflow forever
    timeline = clock.Timeline(t0, t0, period)
    retain_passes(ring, timeline)
    rng = np.random.default_rng(0)
    anchors = t0 + np.arange(0, period, 250_000, dtype=np.int64)
    span = clock.Span(int(anchors[0]), t0 + period - 1)
    for k in range(12):  # twelve passes, in 5 ms batches as a replay pushes them
        t = np.sort(rng.integers(0, period, per_pass)) + t0 + k * period
        for lo in range(0, period, 5_000):
            sel = (t >= t0 + k * period + lo) & (t < t0 + k * period + lo + 5_000)
            n = int(sel.sum())
            ring.push(Events(t[sel], np.zeros(n, np.uint16), np.zeros(n, np.uint16), np.ones(n, np.int8)),
                      complete_until_us=t0 + k * period + lo + 5_000)
        stats = ring.stats()
        assert stats.overflowed == 0
        if k >= 2:
            ranges = clock.renderable(stats.watermark_us, timeline, span, anchors, stats.oldest_us,
                                      bool(stats.overflowed or stats.expired))
            assert ranges == [(span.first_us, span.end_us)], (k, ranges)
    assert ring.stats().expired > 0 and len(ring) <= 3 * per_pass


def test_streams_never_take_a_single_render_slot():
    import asyncio
    import threading

    from edmcgs.server.render_pool import RenderPool

    async def scenario():
        pool = RenderPool(workers=2, queue=8, stream_workers=1)
        release = threading.Event()
        streams = [asyncio.create_task(pool.run_stream(release.wait)) for _ in range(10)]
        await asyncio.sleep(0.05)
        try:
            # Ten streams hold frames in flight: a single render still gets a worker at once.
            assert await asyncio.wait_for(pool.run(lambda: "rendered"), 5) == "rendered"
            assert pool.rejected == 0 and pool.stream_in_flight == 10
        finally:
            release.set()
            await asyncio.gather(*streams)
            pool.close()

    asyncio.run(scenario())


def test_streams_beyond_the_limit_get_busy_and_1013():
    from fastapi.testclient import TestClient
    from starlette.websockets import WebSocketDisconnect

    from edmcgs import protocol
    from edmcgs.server.app import create_app
    from edmcgs.server.settings import Settings

    app = create_app(Settings(max_streams=0, allowed_hosts=["*"]), service_factory=StubService)
    with TestClient(app) as client, client.websocket_connect("/stream") as ws:
        message = protocol.unpack(ws.receive_bytes())
        assert message["type"] == "error" and message["error"] == "busy"
        with pytest.raises(WebSocketDisconnect) as info:
            ws.receive_bytes()
        assert info.value.code == 1013


def test_requests_in_progress_are_capped_not_connections(monkeypatch):
    import uvicorn

    from edmcgs.server import cli
    from edmcgs.server.connections import HeadDeadlineProtocol
    from edmcgs.server.middleware import AccessMiddleware

    seen = {}

    class FakeServer:
        started = True

        def __init__(self, config):
            seen["config"] = config

        def run(self):
            pass

        def handle_exit(self, sig, frame):
            pass

    monkeypatch.setattr(uvicorn, "Server", FakeServer)
    monkeypatch.setattr("edmcgs.server.service.Service.open", lambda settings: StubService(settings))
    monkeypatch.setenv("EDMCGS_MAX_CONNECTIONS", "77")
    monkeypatch.setenv("EDMCGS_PORT", "0")  # the command checks its port is free: 8000 may be taken here
    monkeypatch.setenv("EDMCGS_HEAD_TIMEOUT_S", "3.5")
    assert cli.main([]) == 0
    config = seen["config"]
    assert config.limit_concurrency is None, "uvicorn's limit counts idle connections"
    access = next(m for m in config.app.user_middleware if m.cls is AccessMiddleware)
    assert access.kwargs["max_in_flight"] == 77
    assert issubclass(config.http, HeadDeadlineProtocol) and config.http.head_timeout_s == 3.5


WS_CASES = {
    "mixed_keys": lambda: msgpack.packb({b"fps": 5, "mode": "live"}, use_bin_type=True),
    "400_digit_int": lambda: '{"t0_us": ' + "9" * 400 + "}",
    "t0_1e30": lambda: '{"mode": "sweep", "t0": 1e30}',
    "t0_us_1e30": lambda: '{"mode": "sweep", "t0_us": 1e30}',
    "speed_1e308": lambda: '{"mode": "sweep", "speed": 1e308}',
    "fps_tiny": lambda: '{"mode": "sweep", "fps": 1e-300}',
    "deep_json": lambda: "[" * 5000 + "]" * 5000,
    "deep_msgpack": lambda: msgpack.packb(functools.reduce(lambda a, _: [a], range(500), 1)),
    "huge": lambda: '{"pose": [' + ",".join(["1"] * 40000) + "]}",
}


@pytest.mark.parametrize("case", sorted(WS_CASES))
def test_bad_websocket_messages_get_an_error_and_the_stream_lives_on(stub_client, case):
    from edmcgs import protocol

    with stub_client.websocket_connect("/stream") as ws:
        data = WS_CASES[case]()
        ws.send_bytes(data) if isinstance(data, bytes) else ws.send_text(data)
        answer = protocol.unpack(ws.receive_bytes())
        assert answer["type"] == "error" and answer["error"] == "invalid_input", answer
        ws.send_text('{"fps": 5}')
        assert protocol.unpack(ws.receive_bytes())["type"] == "subscribed"


@pytest.mark.parametrize(("headers", "allowed"), [
    ({}, True),
    ({"origin": "http://127.0.0.1:8000"}, True),
    ({"origin": "http://localhost:5173"}, True),
    ({"origin": "https://evil.example"}, False),
    ({"origin": "null"}, False),
    ({"host": "evil.example:8000"}, False),
    ({"host": "127.0.0.1.evil.example"}, False),
    ({"host": "127.0.0.1:1@evil.com"}, False),
    ({"host": "localhost:8000/evil.com"}, False),
    ({"host": "[::1]:8000"}, True),
    ({"origin": "http://localhost:1@evil.com"}, False),
    ({"origin": "http://user@127.0.0.1:8000"}, False),
    ({"origin": "http://127.0.0.1:8000/evil"}, False),
])
def test_foreign_hosts_and_origins_are_refused_on_loopback(stub_client, headers, allowed):
    from starlette.websockets import WebSocketDisconnect

    response = stub_client.get("/healthz", headers=headers)
    if "origin" not in headers:
        assert response.status_code == (200 if allowed else 421)
    if allowed:
        with stub_client.websocket_connect("/stream", headers=headers) as ws:
            ws.send_text('{"fps": 5}')
            assert ws.receive_bytes()
    else:
        with pytest.raises(WebSocketDisconnect) as info:
            with stub_client.websocket_connect("/stream", headers=headers):
                pass
        assert info.value.code == 1008


def test_loopback_binds_answer_loopback_names_only():
    from edmcgs.server.settings import Settings

    assert sorted(Settings().host_allowlist) == sorted(LOOPBACK)
    assert Settings(host="0.0.0.0").host_allowlist is None


def test_allowed_hosts_are_configurable():
    from fastapi.testclient import TestClient

    from edmcgs.server.app import create_app
    from edmcgs.server.settings import Settings

    app = create_app(Settings(allowed_hosts=["scene.lan"]), service_factory=StubService)
    with TestClient(app, base_url="http://scene.lan:8000") as client:
        assert client.get("/healthz").status_code == 200
        assert client.get("/healthz", headers={"host": "127.0.0.1"}).status_code == 421


@pytest.mark.parametrize("open_probes", [False, True])
def test_probes_and_docs_with_a_token(open_probes):
    from fastapi.testclient import TestClient

    from edmcgs.server.app import create_app
    from edmcgs.server.settings import Settings

    app = create_app(Settings(token="s3cret", open_probes=open_probes), service_factory=StubService)
    # TestClient's HTTP Host is its base_url's: a loopback name
    with TestClient(app, base_url="http://127.0.0.1:8000") as client:
        assert client.get("/docs").status_code == 200
        schema = client.get("/openapi.json")
        assert schema.status_code == 200 and "/render" in schema.json()["paths"]
        for path in ("/healthz", "/metrics"):
            assert client.get(path).status_code == (200 if open_probes else 401)
            assert client.get(path, headers={"Authorization": "Bearer s3cret"}).status_code == 200
        assert client.get("/render").status_code == 401


def test_openapi_states_the_real_limits_and_error_bodies(stub_client):
    schema = stub_client.get("/openapi.json").json()
    params = {p["name"]: p["schema"] for p in schema["paths"]["/render"]["get"]["parameters"]}

    def bound(name, key):
        return next(o[key] for o in params[name]["anyOf"] if key in o)

    assert bound("width", "maximum") == 1920 and bound("width", "minimum") == 1
    assert bound("height", "maximum") == 1920
    assert bound("pose", "maxLength") == 4096
    assert bound("t_us", "maximum") == 2**62 and bound("t_us", "minimum") == -(2**62)
    error_body = {"$ref": "#/components/schemas/ErrorBody"}
    for path in ("/render", "/scene", "/healthz", "/metrics", "/ply"):
        responses = schema["paths"][path]["get"]["responses"]
        for status in ("401", "421", "500"):
            assert responses[status]["content"]["application/json"]["schema"] == error_body
    for path in ("/render", "/ply"):
        responses = schema["paths"][path]["get"]["responses"]
        for status in ("416", "422", "503"):
            assert responses[status]["content"]["application/json"]["schema"] == error_body
    body = schema["components"]["schemas"]["ErrorBody"]
    assert body["title"] == "ErrorBody" and "error" in body["required"]
