"""A checkpoint without an event branch served alone (``edmcgs-serve --checkpoint CKPT``): no source, no
ingest thread, the whole span renderable at once, the head a clock playing the span in a loop."""

from __future__ import annotations

import itertools
import subprocess
import sys
import time

import numpy as np
import pytest

from edmcgs.clients.client import Client, TimeUnavailable
from edmcgs.model.checkpoint import load_checkpoint, read_checkpoint
from edmcgs.server.encode import to_uint8
from harness.server import HEIGHT, WIDTH, ServerProcess, build_scene, metric_values

SPEED = 2.0  # the playback clock runs at twice real time


@pytest.fixture(scope="module")
def sensorless_ckpt(tmp_path_factory):
    """A 2 s scene at 64x48 recorded without events, trained (a few steps) by ``edmcgs train``, which
    leaves the event branch out."""
    folder = tmp_path_factory.mktemp("sensorless")
    rec, _ = build_scene(folder, width=WIDTH, height=HEIGHT, event_rate=0, init_points=500, control_points=32)
    ckpt = folder / "trained.ckpt"
    done = subprocess.run([sys.executable, "-m", "edmcgs.cli", "train", str(rec), "-o", str(ckpt), "--quiet",
                           "--set", "iterations=3", "--set", "init_points=1000", "--set",
                           "num_control_points=32"], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    assert "the recording has no events: training without the event branch" in done.stdout + done.stderr
    assert "no held-out frames to score it on" in done.stdout  # not a NaN PSNR over 0 frames
    lean = read_checkpoint(ckpt)["meta"]["lean"]
    assert lean["event_branch"]["value"] is False
    return ckpt


@pytest.fixture(scope="module")
def server(sensorless_ckpt):
    srv = ServerProcess(["--checkpoint", str(sensorless_ckpt), "--speed", str(SPEED)])
    try:
        srv.wait_ready()
        yield srv
    finally:
        srv.stop()


@pytest.fixture
def client(server):
    with Client(server.url, timeout=20) as c:
        yield c


def test_ready_at_once_with_no_source_and_the_whole_span_renderable(client, server):
    health = client.health()
    assert health["ready"] is True and health["source"] == "none" and health["events_in_ring"] == 0
    scene = client.scene()
    assert scene["source"] is None and scene["has_event_branch"] is False
    first, end = scene["anchors_us"][0], scene["t_end_us"]
    assert scene["renderable_ranges"] == [{"t_min": 0.0, "t_max": (end - first) / 1e6,
                                           "t_us_min": first, "t_us_max": end}]
    assert scene["playback"] == {"speed": SPEED, "period_us": end - first + 1, "loop": True}
    assert first <= scene["head_us"] <= end
    assert "no sensor" in server.log() and "Traceback" not in server.log()


def test_renders_any_time_of_the_span_on_the_checkpoints_anchors(client, sensorless_ckpt):
    model = load_checkpoint(sensorless_ckpt)
    anchors = [int(a) for a in model.meta.anchors_us]
    for t_us in (anchors[0], anchors[3], anchors[3] + 123_457, model.meta.t_end_us):
        image, meta = client.render(t_us=t_us)
        tau = max(a for a in anchors if a <= t_us)
        assert (meta.t_us, meta.anchor_us, meta.events) == (t_us, tau, 0)
        expected = model.render(model.deform(t_us), model.meta.trajectory.at(t_us), model.meta.intrinsics)
        assert np.array_equal(image, to_uint8(expected))  # the server's pixels are the model's
    with pytest.raises(TimeUnavailable) as info:
        client.render(t_us=model.meta.t_end_us + 1)
    assert info.value.status == 416 and "outside the checkpoint's span" in info.value.detail


def test_the_head_is_a_clock_looping_over_the_span(client):
    scene = client.scene()
    period = scene["playback"]["period_us"]
    started = time.monotonic()
    _, a = client.render()  # no t: the head
    deadline = started + 60
    while (b := client.render()[1]).t_us == a.t_us and time.monotonic() < deadline:
        pass
    elapsed = time.monotonic() - started
    moved = (b.t_us - a.t_us) % period  # the clock may have wrapped round the 2 s span
    assert 0 < moved <= elapsed * SPEED * 1e6 + 1  # it moves on, never faster than its speed


def test_metrics_stay_valid_without_a_source(client):
    client.render(t=0.3)
    values = metric_values(client.metrics())
    assert values["edmcgs_up"] == 1.0
    assert values["edmcgs_events_ingested_total"] == 0 and values["edmcgs_ring_events"] == 0
    assert values['edmcgs_events_dropped_total{reason="invalid"}'] == 0
    assert values['edmcgs_http_requests_total{code="200",route="/render"}'] >= 1


def test_sweep_and_live_streams(client):
    scene = client.scene()
    first = scene["anchors_us"][0]
    with client.stream({"mode": "sweep", "t0": 0.0, "t1": 0.5, "fps": 20, "speed": 2.0,
                        "width": 32}) as stream:
        frames = list(stream)
    assert [f.t_us - first for f in frames] == list(range(0, 500_001, 100_000))
    assert all(f.events == 0 and f.image().shape == (24, 32, 3) for f in frames)
    # live: the playback clock's head, frame after frame at the asked rate, always moving on
    with client.stream({"mode": "live", "fps": 10, "width": 32}) as stream:
        started = time.monotonic()
        live = [stream.receive(timeout=10) for _ in range(6)]
        seconds = time.monotonic() - started
    steps = [(b.t_us - a.t_us) % scene["playback"]["period_us"] for a, b in itertools.pairwise(live)]
    assert all(s > 0 for s in steps) and sum(steps) <= seconds * SPEED * 1e6 + 100_000


def test_a_checkpoint_with_an_event_branch_alone_is_refused_naming_the_fix(scene_files):
    _rec, ckpt = scene_files  # the shared scene: trained with events
    done = subprocess.run([sys.executable, "-m", "edmcgs.server.cli", "--checkpoint", str(ckpt),
                           "--port", "0"], capture_output=True, text=True, timeout=120)
    assert done.returncode == 1 and "Traceback" not in done.stderr
    assert "has an event branch" in done.stderr and "--replay REC" in done.stderr


def test_event_maps_are_empty_without_a_sensor(client):
    emap, meta = client.events(t=0.6)
    assert emap.shape == (HEIGHT, WIDTH) and not emap.any() and meta.events == 0
    _image, render = client.render(t=0.6)
    assert (meta.t_us, meta.anchor_us) == (render.t_us, render.anchor_us)
    with pytest.raises(TimeUnavailable):
        client.events(t=5.0)
