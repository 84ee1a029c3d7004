"""GET /render, /scene, /healthz, /metrics against a real edmcgs-serve process, with the real client."""

from __future__ import annotations

import io

import httpx
import numpy as np
import pytest
from PIL import Image

from edmcgs import protocol
from edmcgs.clients.client import Client, InvalidRequest, TimeUnavailable, Unauthorized, depth_metres
from edmcgs.sensor.files.recording import read_recording
from harness.server import HEIGHT, TOKEN, WIDTH, metric_values

AUTH = {"Authorization": f"Bearer {TOKEN}"}
# A pose looking at the scene from 5 cm to the right and tilted by ~11 degrees about y.
SIDE_POSE = [0.05, 0.0, 0.0, 0.995, 0.0, 0.0998, 0.0]


@pytest.fixture(scope="module")
def recording(scene_files):
    return read_recording(scene_files[0])


def test_scene_describes_the_checkpoint_and_the_stream(client, recording):
    scene = client.scene()
    t0 = int(recording.anchors.t_us[0])
    assert scene["t_start_us"] == t0
    assert scene["t_end_us"] == t0 + 2_000_000
    assert scene["duration_s"] == pytest.approx(2.0)
    assert scene["anchors_us"] == [int(t) for t in recording.anchors.t_us]
    assert scene["intrinsics"]["width"] == WIDTH and scene["intrinsics"]["height"] == HEIGHT
    assert scene["intrinsics"]["fx"] == pytest.approx(recording.intrinsics[0])
    traj = scene["trajectory"]
    assert len(traj["t_us"]) == len(traj["c2w"]) == len(recording.trajectory_t_us)
    assert np.allclose(np.asarray(traj["c2w"][-1]).reshape(4, 4), recording.trajectory_c2w[-1], atol=1e-9)
    assert scene["channels"] == 3 and scene["has_event_branch"] is True
    assert scene["t_start_us"] <= scene["head_us"] <= scene["t_end_us"]
    assert scene["source"]["loop"] is True and scene["source"]["period_us"] == 2_000_001
    r = scene["renderable"]
    assert r["t_us_min"] == t0 and r["t_us_min"] <= scene["head_us"] <= r["t_us_max"] + 10_000


@pytest.mark.parametrize("t", [0.0, 0.1, 0.3, 0.45])
def test_render_reports_time_anchor_and_the_exact_event_count(client, recording, t):
    image, meta = client.render(t=t)
    t_us = int(recording.anchors.t_us[0]) + round(t * 1e6)
    anchor = int(recording.anchors.t_us[np.searchsorted(recording.anchors.t_us, t_us, side="right") - 1])
    assert image.shape == (HEIGHT, WIDTH, 3) and image.dtype == np.uint8
    assert meta.t_us == t_us and meta.t == pytest.approx(t)
    assert meta.anchor_us == anchor
    assert meta.events == len(recording.events.time_slice(anchor, t_us))
    assert meta.render_ms > 0
    assert image.std() > 1, "a blank image: the Gaussians are not in view"


def test_pose_changes_the_image_and_renders_are_deterministic(client):
    own, _ = client.render(t=0.3)
    again, _ = client.render(t=0.3)
    side, _ = client.render(t=0.3, pose=SIDE_POSE)
    np.testing.assert_array_equal(own, again)
    assert np.abs(own.astype(int) - side.astype(int)).mean() > 1.0
    # The default pose is the event camera's own pose at t (the checkpoint's trajectory): passing it
    # explicitly, as 16 row-major numbers, gives the same image.
    scene = client.scene()
    t_us = scene["t_start_us"] + 300_000
    i = scene["trajectory"]["t_us"].index(t_us)
    explicit, _ = client.render(t=0.3, pose=scene["trajectory"]["c2w"][i])
    np.testing.assert_array_equal(own, explicit)


def test_formats_agree_and_accept_is_negotiated(client, server):
    raw, meta = client.render(t=0.2, format="msgpack")
    png, png_meta = client.render(t=0.2, format="png")
    jpeg, _ = client.render(t=0.2, format="jpeg")
    np.testing.assert_array_equal(np.asarray(Image.open(io.BytesIO(png))), raw)
    decoded = np.asarray(Image.open(io.BytesIO(jpeg))).astype(int)
    assert np.abs(decoded - raw).mean() < 6  # lossy, but the same picture
    assert (png_meta.width, png_meta.height, png_meta.channels) == (WIDTH, HEIGHT, 3)
    r = httpx.get(server.url + "/render", params={"t": 0.2}, headers=AUTH | {"Accept": "image/jpeg"})
    assert r.status_code == 200 and r.headers["content-type"] == "image/jpeg"
    assert int(r.headers[protocol.HEADER_T_US]) == meta.t_us
    assert {h.lower() for h in protocol.HEADERS} <= set(r.headers)


def test_size_and_aspect(client):
    image, meta = client.render(t=0.2, width=32)
    assert image.shape == (24, 32, 3) and (meta.width, meta.height) == (32, 24)
    image, _ = client.render(t=0.2, width=100, height=30)
    assert image.shape == (30, 100, 3)


def test_t_us_and_t_are_the_same_instant(client):
    scene = client.scene()
    a, ma = client.render(t=0.35)
    b, mb = client.render(t_us=scene["t_start_us"] + 350_000)
    assert ma.t_us == mb.t_us and ma.events == mb.events
    np.testing.assert_array_equal(a, b)


def test_no_time_renders_the_live_head(client):
    before = client.scene()["head_us"]
    _, meta = client.render()
    assert meta.t_us >= before or meta.t_us < before - 1_000_000  # later, or the replay looped
    assert meta.anchor_us <= meta.t_us


@pytest.mark.parametrize(("params", "param"), [
    ({"t": "abc"}, "t"),
    ({"t": "nan"}, "t"),
    ({"t": "0.1", "t_us": "1600000000100000"}, "t"),
    ({"t_us": "1.5"}, "t_us"),
    ({"t": "0.1", "pose": "1,2,3"}, "pose"),
    ({"t": "0.1", "pose": "[1, 2, 3, 4, 5, 6, x]"}, "pose"),
    ({"t": "0.1", "pose": "2,0,0,0, 0,2,0,0, 0,0,2,0, 0,0,0,1"}, "pose"),  # a scaling, not a rotation
    ({"t": "0.1", "pose": "0,0,0,0,0,0,0"}, "pose"),  # zero quaternion
    ({"t": "0.1", "width": "100000"}, "width"),
    ({"t": "0.1", "height": "0"}, "height"),
    ({"t": "0.1", "width": "-5"}, "width"),
    ({"t": "0.1", "format": "gif"}, "format"),
])
def test_bad_parameters_get_422_naming_them(server, params, param):
    r = httpx.get(server.url + "/render", params=params, headers=AUTH, timeout=20)
    assert r.status_code == 422, r.text
    body = r.json()
    assert body["param"] == param
    assert body["detail"]


@pytest.mark.parametrize("t", [-0.5, 2.5, 1e6])
def test_time_outside_what_can_be_rendered_gets_416_with_the_valid_range(client, t):
    with pytest.raises(TimeUnavailable) as info:
        client.render(t=t)
    err = info.value
    assert err.status == 416
    assert "renderable now" in err.detail
    r = err.valid_range
    assert r is not None and r["t_us_min"] <= r["t_us_max"]
    assert 0.0 <= r["t_min"] <= r["t_max"] <= 2.0
    # what the range says is renderable, is
    _, meta = client.render(t_us=r["t_us_min"])
    assert meta.t_us == r["t_us_min"]


def test_client_validates_before_sending(client):
    with pytest.raises(InvalidRequest) as info:
        client.render(t=0.1, pose=[1, 2, 3])
    assert info.value.param == "pose" and info.value.status == 0  # never sent
    with pytest.raises(InvalidRequest) as info:
        client.render(t=0.1, pose=np.eye(4) * 2)  # well-formed, but a scaling: the server's 422
    assert info.value.param == "pose" and info.value.status == 422


def test_every_route_requires_the_token(server):
    for path in ("/docs", "/openapi.json"):  # the schema, no data: /docs must load it with a token set
        assert httpx.get(server.url + path, timeout=10).status_code == 200, path
    for path in ("/scene", "/healthz", "/metrics", "/render?t=0.1", "/"):
        r = httpx.get(server.url + path, timeout=10)
        assert r.status_code == 401, path
        assert r.headers["www-authenticate"].startswith("Bearer")
        wrong = httpx.get(server.url + path, headers={"Authorization": "Bearer wrong"}, timeout=10)
        assert wrong.status_code == 401, path
    assert httpx.get(server.url + "/scene", params={"token": TOKEN}, timeout=10).status_code == 200
    with Client(server.url) as anonymous, pytest.raises(Unauthorized):
        anonymous.scene()
    with Client(server.url, token="wrong") as wrong, pytest.raises(Unauthorized):
        wrong.stream({"mode": "live"})


def test_healthz_and_metrics(client):
    health = client.health()
    assert health["ready"] is True and health["source"] == "streaming" and health["model"] == "loaded"
    assert health["events_in_ring"] > 0
    client.render(t=0.1)
    text = client.metrics()
    values = metric_values(text)
    assert values["edmcgs_up"] == 1.0
    assert values["edmcgs_events_ingested_total"] > 0
    assert values['edmcgs_events_dropped_total{reason="overflow"}'] == 0
    assert 0 < values["edmcgs_ring_fill_ratio"] <= 1
    assert values['edmcgs_http_requests_total{code="200",route="/render"}'] >= 1
    assert values['edmcgs_http_request_duration_seconds_count{route="/render"}'] >= 1
    assert values['edmcgs_http_request_duration_seconds_bucket{le="+Inf",route="/render"}'] >= 1
    assert values['edmcgs_render_seconds_count{path="http"}'] >= 1
    # the stages of every render: each observed once per render, together no longer than the render
    stages = {s: values[f'edmcgs_render_stage_seconds_sum{{stage="{s}"}}']
              for s in ("state", "raster", "encode")}
    renders = values['edmcgs_render_stage_seconds_count{stage="raster"}']
    assert renders >= 1 and all(values[f'edmcgs_render_stage_seconds_count{{stage="{s}"}}'] == renders
                                for s in stages)
    assert all(v > 0 for v in stages.values())
    assert sum(stages.values()) <= values['edmcgs_render_seconds_sum{path="http"}'] + \
        values.get('edmcgs_render_seconds_sum{path="stream"}', 0.0)
    assert "edmcgs_stream_frames_dropped_total" in values
    assert "# TYPE edmcgs_render_seconds histogram" in text


def test_depth_and_alpha_modes_over_http_and_the_stream(client, server):
    """mode=depth: one grey channel with its near and far in the headers (the msgpack map's depth_near /
    depth_far), nearer brighter; mode=alpha: one grey channel; a stream's render_mode the same frames."""
    assert client.scene()["render_modes"] == list(protocol.RENDER_MODES)
    depth, meta = client.render(t=0.3, mode="depth")
    assert depth.shape == (HEIGHT, WIDTH, 1) and meta.render_mode == "depth" and meta.channels == 1
    assert 0 < meta.depth_near < meta.depth_far and not meta.projected
    z = depth_metres(depth, meta)
    covered = ~np.isnan(z)
    assert 0.2 < covered.mean() and (z[covered] >= meta.depth_near - 1e-9).all()
    png, png_meta = client.render(t=0.3, mode="depth", format="png")
    np.testing.assert_array_equal(np.asarray(Image.open(io.BytesIO(png)))[..., None], depth)
    assert (png_meta.depth_near, png_meta.depth_far) == (meta.depth_near, meta.depth_far)  # the headers
    r = httpx.get(server.url + "/render", params={"t": 0.3, "mode": "depth"}, headers=AUTH, timeout=20)
    assert r.headers[protocol.HEADER_MODE] == "depth"
    assert float(r.headers[protocol.HEADER_DEPTH_NEAR]) == meta.depth_near

    alpha, alpha_meta = client.render(t=0.3, mode="alpha")
    assert alpha.shape == (HEIGHT, WIDTH, 1) and alpha_meta.render_mode == "alpha"
    assert alpha_meta.depth_near is None and alpha_meta.depth_far is None
    grey = alpha[..., 0].astype(int)
    clear = np.abs(grey - 255 * protocol.DEPTH_MIN_ALPHA) > 1  # off the threshold's rounding
    np.testing.assert_array_equal((grey >= 128)[clear], covered[clear])  # depth shows where alpha >= 1/2
    rgb, rgb_meta = client.render(t=0.3)
    assert rgb_meta.render_mode == "rgb" and rgb_meta.depth_near is None and rgb.shape[2] == 3
    r = httpx.get(server.url + "/render", params={"t": 0.3}, headers=AUTH, timeout=20)
    assert r.headers[protocol.HEADER_MODE] == "rgb" and protocol.HEADER_DEPTH_NEAR not in r.headers

    sub = {"mode": "sweep", "t0": 0.3, "t1": 0.3, "fps": 10, "format": "raw", "render_mode": "depth"}
    with client.stream(sub) as stream:
        frames = list(stream)
        assert stream.subscription["render_mode"] == "depth"
    assert len(frames) == 1 and frames[0].render_mode == "depth"
    np.testing.assert_array_equal(frames[0].image(), depth)
    assert (frames[0].depth_near, frames[0].depth_far) == (meta.depth_near, meta.depth_far)

    r = httpx.get(server.url + "/render", params={"t": 0.3, "mode": "normals"}, headers=AUTH, timeout=20)
    assert r.status_code == 422 and r.json()["param"] == "mode"
    with pytest.raises(ValueError, match="mode must be one of"):
        client.render(t=0.3, mode="normals")
    with pytest.raises(InvalidRequest) as info:
        client.stream({"render_mode": "normals"})
    assert info.value.param == "render_mode"
