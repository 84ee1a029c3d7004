"""Startup, failure and shutdown of real servers: render failures, a full queue, CLI errors, a real
AEDAT4 replay (no frames: the checkpoint's anchors), and a clean stop with a client connected."""

from __future__ import annotations

import signal
import subprocess
import sys
import threading
import time

import dv_processing as dv
import httpx
import numpy as np
import pytest

from edmcgs.clients.client import Busy, Client, ServerError
from edmcgs.errors import CheckpointError, ReplayFormatError
from edmcgs.server import demo
from edmcgs.server.app import create_app
from edmcgs.server.service import Service
from edmcgs.server.settings import Settings
from harness.server import ServerProcess, ThreadServer, build_scene, metric_values
from tests.support.recordings import write_dvxplorer


def _settings(scene_files, **extra) -> Settings:
    rec, ckpt = scene_files
    return Settings(replay=rec, checkpoint=ckpt, loop=True, **extra)


def _wait_renderable(client: Client, t: float) -> None:
    deadline = time.monotonic() + 10
    while (client.scene()["head_t"] or 0) < t:
        assert time.monotonic() < deadline, "the replay does not advance"
        time.sleep(0.05)


def test_a_failing_render_is_a_500_and_the_server_lives_on(scene_files):
    def faulty(settings: Settings) -> Service:
        service = Service.open(settings)
        render = service.engine.model.render

        def render_or_fail(state, c2w, intrinsics, **kw):
            if intrinsics.width == 13:  # an injected fault, on one size only
                raise RuntimeError("injected rasterizer fault")
            return render(state, c2w, intrinsics, **kw)

        service.engine.model.render = render_or_fail
        return service

    with ThreadServer(create_app(_settings(scene_files), service_factory=faulty)) as srv, \
            Client(srv.url, timeout=20) as client:
        _wait_renderable(client, 0.1)
        with pytest.raises(ServerError) as info:
            client.render(t=0.1, width=13)
        assert info.value.status == 500 and "injected rasterizer fault" in info.value.detail
        image, _ = client.render(t=0.1)
        assert image.shape == (48, 64, 3)
        with client.stream({"mode": "sweep", "t0": 0.1, "t1": 0.1, "loop": True, "width": 13}) as stream:
            with pytest.raises(ServerError, match="injected"):
                stream.receive(timeout=10)
            stream.update(width=32)
            frames = [stream.receive(timeout=10) for _ in range(6)]
            assert frames[-1].width == 32
        assert client.health()["ready"] is True
        text = client.metrics()
        assert metric_values(text)['edmcgs_http_requests_total{code="500",route="/render"}'] == 1


def test_beyond_workers_and_queue_renders_get_503_with_retry_after(scene_files):
    gate = threading.Event()  # admitted renders hold their slot until the test has seen the refusals

    def slow(settings: Settings) -> Service:
        service = Service.open(settings)
        render = service.engine.model.render

        def gated_render(*args, **kw):
            gate.wait(60)
            return render(*args, **kw)

        service.engine.model.render = gated_render
        return service

    settings = _settings(scene_files, render_workers=1, render_queue=1)
    with ThreadServer(create_app(settings, service_factory=slow)) as srv, Client(srv.url) as client:
        _wait_renderable(client, 0.1)
        results = []

        def one():
            try:
                results.append(client.render(t=0.1, format="png")[1])
            except Busy as exc:
                results.append(exc)

        threads = [threading.Thread(target=one) for _ in range(5)]
        for th in threads:
            th.start()
        deadline = time.monotonic() + 60
        while sum(isinstance(r, Busy) for r in results) < 3 and time.monotonic() < deadline:
            time.sleep(0.01)
        gate.set()
        for th in threads:
            th.join(60)
        busy = [r for r in results if isinstance(r, Busy)]
        assert len(results) == 5 and len(busy) == 3, results  # one rendering, one queued, three refused
        assert all(b.status == 503 and b.retry_after_s == 1.0 and "queue is full" in b.detail for b in busy)
        assert metric_values(client.metrics())["edmcgs_renders_rejected_total"] == len(busy)


@pytest.mark.parametrize(("sig", "exit_code"), [
    (signal.SIGINT, 130),  # Ctrl-C: the shell's convention
    (signal.SIGTERM, -signal.SIGTERM),  # docker stop: uvicorn re-raises it after its graceful shutdown
])
def test_a_signal_stops_cleanly_with_a_client_connected(scene_files, sig, exit_code):
    rec, ckpt = scene_files
    srv = ServerProcess(["--replay", str(rec), "--checkpoint", str(ckpt), "--loop"])
    try:
        srv.wait_ready()
        with Client(srv.url) as client, client.stream({"mode": "live", "fps": 20}) as stream:
            assert stream.receive(timeout=10) is not None
            code = srv.stop(sig, timeout=20)
            buffered = 0
            while stream.receive(timeout=10) is not None:  # frames already sent, then the close
                buffered += 1
                assert buffered < 100
    finally:
        srv.stop()
    assert code == exit_code, srv.log()
    log = srv.log()
    assert "stopped: ingest thread joined, source closed" in log
    assert "Traceback" not in log


def _cli(*args: str, env: dict | None = None) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "edmcgs.server.cli", *args], capture_output=True, text=True,
                          timeout=120, env=env)


@pytest.fixture(scope="module")
def aedat4(tmp_path_factory) -> str:
    """A DVXplorer recording (320x240, no frames) written by dv-processing's writer."""
    return str(write_dvxplorer(tmp_path_factory.mktemp("dvx") / "person.aedat4"))


def test_cli_errors_are_one_line(scene_files, aedat4, tmp_path):
    rec, ckpt = scene_files
    missing = _cli("--replay", str(rec), "--checkpoint", str(tmp_path / "nope.ckpt"), "--port", "0")
    assert missing.returncode == 1
    assert "does not exist" in missing.stderr and "Traceback" not in missing.stderr
    looped = _cli("--replay", str(rec), "--loop", "--port", "0")  # no checkpoint: a cold start
    assert looped.returncode == 1 and "a cold start learns one pass of the stream" in looped.stderr
    wrong_size = _cli("--replay", aedat4, "--checkpoint", str(ckpt), "--port", "0")
    assert wrong_size.returncode == 1
    assert "320x240" in wrong_size.stderr and "64x48" in wrong_size.stderr
    live = _cli("--live", "--checkpoint", str(ckpt), "--port", "0")  # no DAVIS on this machine
    assert live.returncode == 1 and "no camera found" in live.stderr and "Traceback" not in live.stderr


def test_missing_demo_says_how_to_serve_a_scene(monkeypatch, tmp_path):
    monkeypatch.setattr(demo, "CHECKPOINT", tmp_path / "scene.ckpt")
    monkeypatch.setattr(demo, "RECORDING", tmp_path / "scene.h5")
    with pytest.raises(CheckpointError, match=r"--replay REC.h5 --checkpoint CKPT"):
        demo.files()


@pytest.fixture(scope="module")
def aedat_checkpoint(tmp_path_factory, aedat4):
    """A checkpoint on the AEDAT4 file's own clock and resolution (its first 0.5 s)."""
    first, _last = dv.io.MonoCameraRecording(aedat4).getTimeRange()
    _rec, ckpt = build_scene(tmp_path_factory.mktemp("aedat"), width=320, height=240, duration_s=0.5,
                             anchor_every_s=0.1, event_rate=1000, init_points=2000, control_points=64,
                             t0_us=int(first))
    return int(first), ckpt


def test_replays_a_real_aedat4_on_the_checkpoints_anchors(aedat_checkpoint, aedat4):
    first, ckpt = aedat_checkpoint
    reader = dv.io.MonoCameraRecording(aedat4)
    times = []
    while (batch := reader.getNextEventBatch()) is not None:
        times.append(batch.numpy()["timestamp"])
    times = np.concatenate(times)
    srv = ServerProcess(["--replay", aedat4, "--checkpoint", str(ckpt), "--speed", "2"])
    try:
        srv.wait_ready()
        with Client(srv.url) as client:
            scene = client.scene()
            assert scene["source"]["has_frames"] is False and scene["t_start_us"] == first
            _wait_renderable(client, 0.35)
            image, meta = client.render(t=0.35)
            anchor = first + 300_000  # anchors every 0.1 s: the checkpoint's, the file has no frames
            assert meta.anchor_us == anchor
            expected = int(np.count_nonzero((times >= anchor) & (times < first + 350_000)))
            assert expected > 0 and meta.events == expected
            assert image.shape == (240, 320, 3)
    finally:
        srv.stop()


def test_a_failing_source_makes_healthz_503_and_keeps_what_was_buffered(scene_files):
    def failing_source(settings: Settings) -> Service:
        service = Service.open(settings)
        read, calls = service.source.read, [0]

        def read_then_fail():
            calls[0] += 1
            if calls[0] > 60:  # ~0.3 s of the recording in, an injected I/O failure
                raise ReplayFormatError("injected: the recording became unreadable")
            return read()

        service.source.read = read_then_fail
        return service

    with ThreadServer(create_app(_settings(scene_files), service_factory=failing_source)) as srv, \
            Client(srv.url) as client:
        deadline = time.monotonic() + 20
        while httpx.get(srv.url + "/healthz", timeout=10).status_code == 200:
            assert time.monotonic() < deadline, "the source failure never showed"
            time.sleep(0.05)
        r = httpx.get(srv.url + "/healthz", timeout=10)
        assert r.status_code == 503 and r.headers["retry-after"] == "1"
        body = r.json()
        assert body["ready"] is False and body["source"] == "error" and "injected" in body["source_error"]
        _, meta = client.render(t=0.2)  # the events already in the ring still render
        assert meta.events > 0
        assert metric_values(client.metrics())["edmcgs_up"] == 0
