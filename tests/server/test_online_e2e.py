"""Live past the checkpoint: ``edmcgs-serve --replay LONG --checkpoint SHORT`` renders at the stream's
head to the recording's end, the stream's frames past the span becoming online anchors (GET /scene's
``online``), corrected in the background with fits that fall behind skipped and counted (GET /metrics),
and a long looping replay keeps its memory bounded."""

from __future__ import annotations

import time

import httpx
import numpy as np
import pytest

from edmcgs import protocol
from edmcgs.clients.client import Client
from harness.server import HEIGHT, WIDTH, ServerProcess, build_scene, metric_values

TRAIN_S, DURATION_S = 0.5, 2.5  # the stream is 5x the checkpoint's span


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    """2.5 s at 64x48 with frames every 50 ms; the checkpoint covers its first 0.5 s."""
    return build_scene(tmp_path_factory.mktemp("online_e2e"), width=WIDTH, height=HEIGHT,
                       duration_s=DURATION_S, anchor_every_s=0.1, frames_per_anchor=2, event_rate=20_000,
                       init_points=1500, control_points=48, event_branch_seed=0, train_s=TRAIN_S)


def test_a_stream_five_times_the_span_renders_at_its_head_to_the_end(scene):
    rec, ckpt = scene
    srv = ServerProcess(["--replay", str(rec), "--checkpoint", str(ckpt)],
                        env={"EDMCGS_ONLINE_FIT_STEPS": "4"})
    try:
        srv.wait_ready()
        with Client(srv.url, timeout=30) as client:
            info = client.scene()
            t0, end = info["t_start_us"], info["t_end_us"]
            assert end - t0 == TRAIN_S * 1e6
            last = t0 + round(DURATION_S * 1e6)
            heads, kinds = [], set()
            deadline = time.monotonic() + 60
            while True:
                _, meta = client.render(format="msgpack")  # the head, the event camera's view
                heads.append(meta.t_us)
                kinds.add(meta.anchor)
                # past the span it is projected onto the events since its anchor's frame (before the
                # first online anchor: the frame at the checkpoint's last anchor)
                assert meta.projected == (meta.t_us > end)
                if meta.t_us >= last - 1:
                    break
                assert time.monotonic() < deadline, f"the head stopped at {meta.t_us - t0} µs"
                time.sleep(0.05)
            assert heads == sorted(heads) and heads[-1] >= last - 1
            assert any(h > end for h in heads[:-1])  # it rendered past the span while streaming
            assert kinds <= set(protocol.ANCHOR_KINDS) and kinds & {"predicted", "corrected"}

            info = client.scene()
            online = info["online"]
            assert [e["source"] for e in info["tau_sources"]] == ["checkpoint", "online"]
            assert info["tau_sources"][1]["t_us_max"] == info["head_us"] >= last - 1
            times = [a["t_us"] for a in online["anchors"]]
            assert times == sorted(times) and times[0] == end + 50_000 and times[-1] == last
            assert len(times) == online["predicted"] == 40
            assert online["refused"] == {"size": 0, "channels": 0, "timestamp": 0} and online["project"]
            assert online["span"]["t_us_min"] == times[0] and online["span"]["t_us_max"] == last
            # the newest anchor's window: renders after the end of the training span use it
            pixels, meta = client.render(t_us=last, format="msgpack")
            assert meta.anchor_us == last and meta.anchor in ("predicted", "corrected")
            assert pixels.shape == (HEIGHT, WIDTH, 3)
            _, meta = client.render(t_us=times[3] + 20_000, format="msgpack")
            assert meta.anchor_us == times[3] and meta.events > 0 and meta.projected
            _, meta = client.render(t_us=times[3] + 20_000, format="png")  # the header says it too
            assert meta.projected
            _, meta = client.render(t_us=times[3] + 20_000, pose=np.eye(4), format="png")  # another view
            assert not meta.projected

            # fitting: every anchor is corrected, skipped (superseded) or still queued; all counted
            deadline = time.monotonic() + 60
            while client.scene()["online"]["queue_depth"] and time.monotonic() < deadline:
                time.sleep(0.2)
            online = client.scene()["online"]
            assert online["corrected"] >= 1 and online["fit"]["last_s"] > 0
            assert online["fit"]["colour_lr"] == 0.01  # the corrections learn colours by default
            assert online["corrected"] + online["skipped"]["superseded"] == online["predicted"]
            # what moves the anchors past the span, chosen by the frames the fits saw
            moves = online["transition"]
            assert moves["mode"] == "select" and moves["current"] in moves["evidence"]
            assert set(moves["evidence"]) == {"g_phi", "none"}  # this checkpoint has no distilled one
            assert all(v is None or np.isfinite(v) for v in moves["evidence"].values())
            values = metric_values(client.metrics())
            assert values['edmcgs_online_anchors_total{result="corrected"}'] == online["corrected"]
            assert values['edmcgs_online_anchors_skipped_total{reason="superseded"}'] == \
                online["skipped"]["superseded"]
            assert values["edmcgs_online_fit_seconds_count"] == online["corrected"]
            assert values["edmcgs_online_fit_queue_depth"] == 0
            assert 'edmcgs_frames_refused_total{reason="size"}' in values
            # beyond the head: 416 naming what can be rendered
            r = httpx.get(srv.url + "/render", params={"t_us": last + 10**6})
            assert r.status_code == 416 and r.json()["valid_range"]["t_us_max"] == info["head_us"]
    finally:
        srv.stop()


def test_fitting_that_falls_behind_skips_and_memory_stays_bounded_on_a_long_loop(scene):
    rec, ckpt = scene
    # 8x real time with 40-step fits at full size: the fit cannot keep up with 20 frames a second
    srv = ServerProcess(["--replay", str(rec), "--checkpoint", str(ckpt), "--loop", "--speed", "8"],
                        env={"EDMCGS_ONLINE_FIT_STEPS": "40", "EDMCGS_ONLINE_FIT_SCALE": "1",
                             "EDMCGS_ONLINE_ANCHORS": "8"})
    try:
        srv.wait_ready()
        with Client(srv.url, timeout=30) as client:
            period = None
            rss = []
            for _ in range(6):  # six samples over ~6 passes of the recording
                deadline = time.monotonic() + 60
                start = client.scene()["stream_head_us"]
                while True:
                    info = client.scene()
                    period = info["source"]["period_us"]
                    if info["stream_head_us"] >= start + period:
                        break
                    assert time.monotonic() < deadline
                    time.sleep(0.2)
                online = info["online"]
                assert len(online["anchors"]) <= 8
                pixels, _ = client.render(format="msgpack")  # the head renders on every pass
                assert pixels.shape == (HEIGHT, WIDTH, 3)
                rss.append(srv.rss_mb())
            assert online["predicted"] > 5 * 40 and online["expired"] >= online["predicted"] - 8
            assert online["skipped"]["superseded"] > 0  # fell behind: skipped, counted
            assert online["corrected"] + online["skipped"]["superseded"] <= online["predicted"]
            assert online["queue_depth"] <= 2
            values = metric_values(client.metrics())
            assert values['edmcgs_online_anchors_skipped_total{reason="superseded"}'] > 0
            # bounded: the last passes add nothing noticeable once the ring and stores are full
            assert max(rss[2:]) - rss[2] < 60, rss
    finally:
        srv.stop()


def test_a_checkpoint_drawn_in_anchor_windows_over_a_layer_renders_past_its_span(tmp_path):
    # the real preset's switches: online anchors carry the last window's Gaussians over the layer
    rec, ckpt = build_scene(tmp_path, width=WIDTH, height=HEIGHT, duration_s=1.5, anchor_every_s=0.1,
                            frames_per_anchor=2, event_rate=20_000, init_points=1000, control_points=32,
                            event_branch_seed=0, train_s=TRAIN_S,
                            config_overrides={"anchor_windows": True, "bg_layer": True,
                                              "dynamic_threshold": 0.06})
    srv = ServerProcess(["--replay", str(rec), "--checkpoint", str(ckpt), "--online-spawn", "50",
                         "--online-finetune-steps", "2"], env={"EDMCGS_ONLINE_FIT_STEPS": "4"})
    try:
        srv.wait_ready()
        with Client(srv.url, timeout=30) as client:
            info = client.scene()
            last = info["t_start_us"] + round(1.5e6)
            deadline = time.monotonic() + 60
            while client.scene()["head_us"] < last - 1:
                assert time.monotonic() < deadline
                time.sleep(0.1)
            deadline = time.monotonic() + 60
            while client.scene()["online"]["queue_depth"] and time.monotonic() < deadline:
                time.sleep(0.2)
            online = client.scene()["online"]
            assert online["predicted"] == 20 and online["corrected"] >= 1
            assert online["corrected"] + online["skipped"]["superseded"] == online["predicted"]
            pixels, meta = client.render(t_us=last, format="msgpack")
            assert meta.anchor_us == last and meta.anchor in ("predicted", "corrected")
            assert pixels.shape == (HEIGHT, WIDTH, 3) and pixels.std() > 0
    finally:
        srv.stop()
