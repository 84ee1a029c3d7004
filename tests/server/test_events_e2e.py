"""GET /events and /scene's training views against a real edmcgs-serve process, with the real client."""

from __future__ import annotations

import io

import httpx
import numpy as np
import pytest
from PIL import Image

from edmcgs import protocol
from edmcgs.clients.client import TimeUnavailable
from edmcgs.model.checkpoint import load_checkpoint
from edmcgs.sensor.event_map import accumulate
from edmcgs.sensor.files.recording import read_recording
from harness.server import HEIGHT, TOKEN, WIDTH

AUTH = {"Authorization": f"Bearer {TOKEN}"}


@pytest.fixture(scope="module")
def recording(scene_files):
    return read_recording(scene_files[0])


def _window(recording, t: float) -> tuple[int, int]:
    t_us = int(recording.anchors.t_us[0]) + round(t * 1e6)
    anchors = recording.anchors.t_us
    return int(anchors[np.searchsorted(anchors, t_us, side="right") - 1]), t_us


@pytest.mark.parametrize("t", [0.1, 0.3, 0.45, 1.99])
def test_event_map_is_the_signed_sum_of_the_window_a_render_uses(client, recording, t):
    emap, meta = client.events(t=t)
    anchor, t_us = _window(recording, t)
    window = recording.events.time_slice(anchor, t_us)
    assert emap.shape == (HEIGHT, WIDTH) and emap.dtype == np.int32
    np.testing.assert_array_equal(emap, accumulate(window, WIDTH, HEIGHT).astype(np.int32))
    assert (meta.t_us, meta.anchor_us, meta.events) == (t_us, anchor, len(window))
    assert meta.t == pytest.approx(t) and (meta.width, meta.height) == (WIDTH, HEIGHT)
    assert (emap > 0).any() and (emap < 0).any()
    _image, render = client.render(t=t)
    assert (render.t_us, render.anchor_us, render.events) == (meta.t_us, meta.anchor_us, meta.events)


def test_png_is_the_dv_picture_of_the_same_map(client):
    emap, _ = client.events(t=0.4)
    png, meta = client.events(t=0.4, format="png")
    rgba = np.asarray(Image.open(io.BytesIO(png)))
    assert rgba.shape == (HEIGHT, WIDTH, 4) and meta.events > 0
    assert (rgba[emap > 0] == [*protocol.EVENT_ON_RGB, 255]).all()
    assert (rgba[emap < 0] == [*protocol.EVENT_OFF_RGB, 255]).all()
    assert (rgba[emap == 0, 3] == 0).all()


def test_at_an_anchor_the_window_is_empty_and_without_a_time_it_is_the_heads(client, recording):
    emap, meta = client.events(t=0.25)
    assert meta.events == 0 and meta.anchor_us == meta.t_us and not emap.any()
    _emap, head = client.events()
    scene = client.scene()
    assert scene["t_start_us"] <= head.t_us <= scene["head_us"]


def test_accept_negotiates_and_the_media_types_are_stated(server):
    r = httpx.get(server.url + "/events", params={"t": "0.3"},
                  headers={**AUTH, "Accept": "application/msgpack"}, timeout=20)
    assert r.status_code == 200 and r.headers["content-type"] == "application/msgpack"
    assert protocol.unpack(r.content)["type"] == "event_map"
    r = httpx.get(server.url + "/events", params={"t": "0.3"}, headers=AUTH, timeout=20)
    assert r.status_code == 200 and r.headers["content-type"] == "image/png"
    assert r.headers["cache-control"] == "no-store"
    assert httpx.get(server.url + "/events", params={"t": "0.3"}, timeout=20).status_code == 401


@pytest.mark.parametrize("t", [-0.5, 5.0])
def test_time_outside_what_can_be_rendered_gets_416_with_the_valid_range(client, t):
    with pytest.raises(TimeUnavailable) as info:
        client.events(t=t)
    err = info.value
    assert err.status == 416 and err.valid_range is not None
    assert err.valid_range["t_min"] <= err.valid_range["t_max"]


def test_scene_lists_the_training_views(client, scene_files):
    views = client.scene()["training_views"]
    model = load_checkpoint(scene_files[1])
    np.testing.assert_allclose(views["center"], model.center.numpy(), rtol=1e-6)
    traj = model.meta.trajectory
    c2w = np.array(views["c2w"]).reshape(-1, 4, 4)
    assert len(c2w) == len(traj.t_us)  # 201 samples over 2 s: under the cap, all listed
    np.testing.assert_allclose(c2w, traj.c2w)
    distances = np.linalg.norm(traj.c2w[:, :3, 3] - model.center.numpy(), axis=1)
    assert views["scale"] == pytest.approx(float(np.median(distances)), rel=1e-6)
