"""WS /stream against a real edmcgs-serve process, with the real client."""

from __future__ import annotations

import itertools
import json
import socket
import time

import numpy as np
import pytest
from websockets.sync.client import connect

from edmcgs import protocol
from edmcgs.clients.client import InvalidRequest
from edmcgs.sensor.files.recording import read_recording
from harness.server import HEIGHT, TOKEN, WIDTH, metric_values

SIDE_POSE = [0.05, 0.0, 0.0, 0.995, 0.0, 0.0998, 0.0]


def test_sweep_renders_every_step_then_ends(client, scene_files):
    rec = read_recording(scene_files[0])
    t_start = int(rec.anchors.t_us[0])
    with client.stream({"mode": "sweep", "t0": 0.1, "t1": 0.4, "fps": 20, "format": "raw"}) as stream:
        frames = list(stream)
        assert stream.subscription["mode"] == "sweep"
    assert [f.t_us for f in frames] == [t_start + k * 50_000 for k in range(2, 9)]
    assert [f.seq for f in frames] == list(range(7)) and frames[-1].dropped == 0
    for f in frames:
        image = f.image()
        assert image.shape == (HEIGHT, WIDTH, 3) and f.format == "raw"
        anchor = int(rec.anchors.t_us[np.searchsorted(rec.anchors.t_us, f.t_us, side="right") - 1])
        assert f.anchor_us == anchor
        assert f.events == len(rec.events.time_slice(anchor, f.t_us))
        assert f.arrived_unix_us is None and f.head_arrived_unix_us is None  # a sweep is not the live head


def test_sweep_frames_equal_http_renders(client):
    with client.stream({"mode": "sweep", "t0": 0.25, "t1": 0.3, "fps": 30, "format": "png"}) as stream:
        frames = list(stream)
    for f in frames:
        pixels, _ = client.render(t_us=f.t_us)
        np.testing.assert_array_equal(f.image(), pixels)


def test_live_follows_the_head(client):
    with client.stream({"mode": "live", "fps": 30, "format": "jpeg"}) as stream:
        frames = [stream.receive(timeout=10) for _ in range(12)]
    assert all(f is not None for f in frames)
    assert [f.seq for f in frames] == sorted(f.seq for f in frames)
    times = [f.t_us for f in frames]
    forward = sum(b > a for a, b in itertools.pairwise(times))
    assert forward >= len(times) - 2, times  # the head moves on (one loop wrap allowed)
    now_us = time.time_ns() // 1000
    for f in frames:
        assert f.arrived_unix_us is not None and 0 <= now_us - f.arrived_unix_us < 10_000_000
        # the frame's time came with its newest batch: never before its oldest new event's
        assert f.arrived_unix_us <= f.head_arrived_unix_us <= now_us
        assert f.anchor_us <= f.t_us
        assert f.image().shape == (HEIGHT, WIDTH, 3)


def test_pose_can_change_mid_stream(client):
    own, _ = client.render(t=0.3)
    side, _ = client.render(t=0.3, pose=SIDE_POSE)
    sub = {"mode": "sweep", "t0": 0.3, "t1": 0.3, "loop": True, "fps": 30, "format": "raw"}
    with client.stream(sub) as stream:
        np.testing.assert_array_equal(stream.receive(timeout=10).image(), own)
        stream.update(pose=SIDE_POSE)
        seen = [stream.receive(timeout=10).image() for _ in range(6)]
    # A frame already rendering when the update arrived may still show the old pose; then the new one.
    firsts = [i for i, image in enumerate(seen) if np.array_equal(image, side)]
    assert firsts and firsts[0] <= 2
    assert all(np.array_equal(image, side) for image in seen[firsts[0]:])


def test_bad_subscription_gets_an_error_and_the_stream_goes_on(client):
    with client.stream({"mode": "sweep", "t0": 0.1, "t1": 0.1, "loop": True, "fps": 20}) as stream:
        assert stream.receive(timeout=10) is not None
        stream.update(fps=-1)
        with pytest.raises(InvalidRequest) as info:
            for _ in range(10):
                stream.receive(timeout=10)
        assert info.value.param == "fps"
        stream.update(width=100000)
        with pytest.raises(InvalidRequest) as info:
            for _ in range(10):
                stream.receive(timeout=10)
        assert info.value.param == "width"
        stream.update(width=32)
        frames = [stream.receive(timeout=10) for _ in range(8)]
        assert frames[-1].width == 32 and frames[-1].height == 24


def test_raw_json_and_msgpack_subscriptions(server):
    url = server.url.replace("http", "ws") + f"/stream?token={TOKEN}"
    with connect(url, open_timeout=10) as ws:
        ws.send(json.dumps({"mode": "sweep", "t0": 0.2, "t1": 0.2, "fps": 10, "bogus": 1}))
        error = protocol.unpack(ws.recv(timeout=10))
        assert error["type"] == "error" and error["param"] == "bogus"
        ws.send("not json")
        assert protocol.unpack(ws.recv(timeout=10))["type"] == "error"
        ws.send(protocol.pack({"mode": "sweep", "t0": 0.2, "t1": 0.2, "fps": 10}))
        kinds = [protocol.unpack(ws.recv(timeout=10))["type"] for _ in range(3)]
        assert kinds == ["subscribed", "frame", "end"] or kinds == ["frame", "subscribed", "end"]
    with connect(server.url.replace("http", "ws") + "/stream", open_timeout=10,
                 additional_headers={"Authorization": f"Bearer {TOKEN}"}) as ws:
        ws.send(protocol.pack({"mode": "sweep", "t0": 5.0, "t1": 5.0, "fps": 10}))  # outside the span
        messages = [protocol.unpack(ws.recv(timeout=10)) for _ in range(3)]
        errors = [m for m in messages if m["type"] == "error"]
        assert errors and errors[0]["error"] == protocol.ErrorCode.TIME_UNAVAILABLE
        assert errors[0]["valid_range"]


def _metrics(client) -> dict[str, float]:
    return metric_values(client.metrics())


def test_a_client_that_stops_reading_costs_no_renders_and_is_dropped(client, server):
    """A client whose socket takes nothing more: no frame is rendered it cannot take, the memory does
    not grow with the stall, and it is dropped once it leaves the keepalive pings unanswered (its
    stream slot given back)."""
    produced = 'edmcgs_render_seconds_count{path="stream"}'
    sent, streams = "edmcgs_stream_frames_sent_total", "edmcgs_stream_clients"
    sock = socket.socket()
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 8192)  # a receiver that soon stops taking data
    sock.connect(("127.0.0.1", server.port))
    url = server.url.replace("http", "ws") + f"/stream?token={TOKEN}"
    with connect(url, sock=sock, max_queue=1, max_size=2**24, open_timeout=10, ping_interval=None) as ws:
        ws.send(protocol.pack({"mode": "sweep", "t0": 0.2, "t1": 0.2, "loop": True, "fps": 30,
                               "format": "raw", "width": 320, "height": 240}))  # 230 kB frames
        for _ in range(3):
            ws.recv(timeout=10)
        before, rss_before = _metrics(client), server.rss_mb()
        deadline = time.monotonic() + 30
        while (after := _metrics(client))[streams] > before[streams] - 1 and time.monotonic() < deadline:
            time.sleep(0.1)  # read nothing: the server stops rendering for it, then drops it
        rss_after = server.rss_mb()
        assert after[streams] == before[streams] - 1, "the stream keeps its slot"
        assert after[produced] - before[produced] <= after[sent] - before[sent] + 2, "rendered, never sent"
        assert after[produced] - before[produced] < 30 * (time.monotonic() - deadline + 30) / 2
        assert rss_after - rss_before < 40, (rss_before, rss_after)


def test_a_slow_reader_gets_frames_with_the_skipped_ones_counted(server):
    """A client that takes four frames a second of a 30 fps subscription: the ticks it is too slow for
    are not rendered but counted in ``dropped`` (``seq`` has gaps), and it keeps its stream (it answers
    the pings, late, behind the frames queued to it)."""
    sock = socket.socket()
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 8192)  # frames wait at the server, not here
    sock.connect(("127.0.0.1", server.port))
    url = server.url.replace("http", "ws") + f"/stream?token={TOKEN}"
    with connect(url, sock=sock, max_queue=1, max_size=2**24, open_timeout=10) as ws:
        ws.send(protocol.pack({"mode": "sweep", "t0": 0.2, "t1": 0.2, "loop": True, "fps": 30,
                               "format": "raw", "width": 320, "height": 240}))  # 230 kB frames
        frames = []
        while not frames or frames[-1]["dropped"] < 3:  # what the socket buffers held, then the drops
            message = protocol.unpack(ws.recv(timeout=10))
            if message["type"] == "frame":
                frames.append(message)
                time.sleep(0.25)
            assert len(frames) < 100, frames[-1]["dropped"]
    seqs = [f["seq"] for f in frames]
    assert seqs[-1] - seqs[0] + 1 > len(seqs), seqs
