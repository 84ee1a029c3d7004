"""GET /events and /scene's training views at unit level: the DV-style picture, the event-map wire
map, the route's parameter errors and schema (no render reached), and the training views."""

from __future__ import annotations

import io
import types

import numpy as np
import pytest
import torch
from PIL import Image

from edmcgs import protocol
from edmcgs.geometry import Trajectory
from edmcgs.server.encode import encode, event_rgba
from edmcgs.server.settings import LOOPBACK
from edmcgs.server.views import MAX_VIEWS, training_views
from tests.support.stub import StubService


def test_event_picture_is_blue_for_on_red_for_off_and_clear_elsewhere():
    emap = np.array([[3, -1, 0], [0, 1, -7]], np.int32)
    rgba = event_rgba(emap)
    assert rgba.shape == (2, 3, 4) and rgba.dtype == np.uint8
    np.testing.assert_array_equal(rgba[0, 0], [*protocol.EVENT_ON_RGB, 255])
    np.testing.assert_array_equal(rgba[1, 1], [*protocol.EVENT_ON_RGB, 255])
    np.testing.assert_array_equal(rgba[0, 1], [*protocol.EVENT_OFF_RGB, 255])
    np.testing.assert_array_equal(rgba[1, 2], [*protocol.EVENT_OFF_RGB, 255])
    assert rgba[0, 2, 3] == 0 and rgba[1, 0, 3] == 0
    on, off = np.array(protocol.EVENT_ON_RGB), np.array(protocol.EVENT_OFF_RGB)
    assert on[2] > on[0] + 100 and off[0] > off[2] + 100  # blue and red, told apart at a glance
    back = np.asarray(Image.open(io.BytesIO(encode(rgba, "png"))))
    np.testing.assert_array_equal(back, rgba)  # the PNG keeps the alpha channel
    with pytest.raises(ValueError, match=r"\[H, W\]"):
        event_rgba(np.zeros((2, 2, 2)))


def test_event_map_message_round_trips():
    emap = np.arange(-6, 6, dtype=np.int32).reshape(3, 4)
    meta = protocol.EventMapMeta(t_us=1_700_000_000_250_000, t=0.25, anchor_us=1_700_000_000_000_000,
                                 events=42, width=4, height=3)
    message = protocol.unpack(protocol.pack(meta.to_message(emap.astype(protocol.EVENT_MAP_DTYPE).tobytes())))
    assert tuple(message) == protocol.EVENT_MAP_KEYS
    assert protocol.EventMapMeta.from_message(message) == meta
    data = np.frombuffer(message["data"], protocol.EVENT_MAP_DTYPE)
    np.testing.assert_array_equal(data.reshape(3, 4), emap)
    assert protocol.EventMapMeta.from_headers(meta.headers()) == meta
    assert tuple(meta.headers()) == protocol.EVENT_HEADERS
    with pytest.raises(ValueError, match="48 bytes"):
        meta.to_message(b"\x00" * 12)
    with pytest.raises(protocol.ProtocolError, match="not an event map"):
        protocol.EventMapMeta.from_message({**message, "type": "frame"})


def _model(poses: np.ndarray, t_us: np.ndarray, *, span=None, center=(0.0, 0.0, 2.0), extent=0.7):
    lo, hi = span or (int(t_us[0]), int(t_us[-1]))
    meta = types.SimpleNamespace(trajectory=Trajectory(t_us, poses), t_start_us=lo, t_end_us=hi)
    return types.SimpleNamespace(meta=meta, center=torch.tensor(center, dtype=torch.float32),
                                 extent=torch.tensor(extent))


def _slide(n: int) -> np.ndarray:
    poses = np.repeat(np.eye(4)[None], n, axis=0)
    poses[:, 0, 3] = np.linspace(-0.5, 0.5, n)
    return poses


def test_training_views_are_the_trajectory_over_the_span_with_the_scale_of_the_scene():
    poses, t_us = _slide(11), 1_000_000 + 100_000 * np.arange(11, dtype=np.int64)
    views = training_views(_model(poses, t_us, span=(1_200_000, 1_800_000)))
    assert views["center"] == pytest.approx([0.0, 0.0, 2.0])
    got = np.array(views["c2w"]).reshape(-1, 4, 4)
    np.testing.assert_allclose(got, poses[2:9])  # the trajectory's samples within the span
    # the median distance of those cameras from the centre
    assert views["scale"] == pytest.approx(np.median(np.hypot(got[:, 0, 3], 2.0)))


def test_a_long_trajectory_is_thinned_evenly_to_its_ends():
    n = 5000
    poses, t_us = _slide(n), np.arange(n, dtype=np.int64) * 1000
    views = training_views(_model(poses, t_us))
    got = np.array(views["c2w"]).reshape(-1, 4, 4)
    assert len(got) == MAX_VIEWS
    np.testing.assert_allclose(got[[0, -1]], poses[[0, -1]])
    assert np.diff(got[:, 0, 3]).max() < 2.5 * (1.0 / MAX_VIEWS)  # no gap in the path


def test_cameras_at_the_centre_take_the_models_extent_and_no_trajectory_gives_none():
    views = training_views(_model(np.eye(4)[None], np.array([5], np.int64), center=(0.0, 0.0, 0.0)))
    assert views["scale"] == pytest.approx(0.7)
    no_traj = types.SimpleNamespace(meta=types.SimpleNamespace(trajectory=None))
    assert training_views(no_traj) is None


# ------------------------------------------------------------------ the route, before any render

class _Service(StubService):
    def event_map(self, t_us, fmt):
        raise AssertionError("a malformed request reached the event map")


@pytest.fixture
def app_client():
    from fastapi.testclient import TestClient

    from edmcgs.server.app import create_app
    from edmcgs.server.settings import Settings

    app = create_app(Settings(allowed_hosts=[*LOOPBACK, "testserver"]), service_factory=_Service)
    with TestClient(app, base_url="http://127.0.0.1:8000") as client:
        yield client


@pytest.mark.parametrize(("params", "param"), [
    ({"t": "0.1", "t_us": "1600000000100000"}, "t"),
    ({"t": "soon"}, "t"),
    ({"t_us": str(2**63)}, "t_us"),
    ({"format": "jpeg"}, "format"),
])
def test_malformed_parameters_get_422_naming_them(app_client, params, param):
    response = app_client.get("/events", params=params)
    assert response.status_code == 422, response.text
    body = response.json()
    assert body["error"] == "invalid_input" and body["param"] == param, body


def test_openapi_documents_the_route_its_bodies_and_errors(app_client):
    schema = app_client.get("/openapi.json").json()
    get = schema["paths"]["/events"]["get"]
    assert {p["name"] for p in get["parameters"]} == {"t", "t_us", "format"}
    ok = get["responses"]["200"]
    assert set(ok["content"]) == {"image/png", "application/msgpack"}
    for body in ok["content"].values():
        assert body["schema"]["type"] == "string" and body["schema"]["format"] == "binary"
    assert all(key in ok["content"]["application/msgpack"]["schema"]["description"]
               for key in protocol.EVENT_MAP_KEYS)
    assert set(ok["headers"]) == set(protocol.EVENT_HEADERS)
    for status in ("401", "416", "422", "503"):
        body = get["responses"][status]["content"]["application/json"]["schema"]
        assert body == {"$ref": "#/components/schemas/ErrorBody"}
