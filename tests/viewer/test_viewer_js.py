"""The viewer's own JavaScript, run in the real browser: the msgpack decoder against Python's msgpack,
the pose math against scipy, and the page's report of a server that has no scene.

Served here by a plain static file server of the viewer's folder, at / as edmcgs-serve mounts it,
with no API behind it (every API route: 404).
"""

from __future__ import annotations

import functools
import http.server
import json
import math
import threading

import msgpack
import numpy as np
import pytest
from scipy.spatial.transform import Rotation, Slerp

from tests.support.viewer import VIEWER


class _StaticViewer(http.server.SimpleHTTPRequestHandler):
    def log_message(self, *args):
        pass


@pytest.fixture(scope="module")
def static_url():
    handler = functools.partial(_StaticViewer, directory=str(VIEWER))
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    try:
        yield f"http://127.0.0.1:{server.server_port}/"
    finally:
        server.shutdown()
        server.server_close()
        thread.join(5)


@pytest.fixture
def viewer(page, static_url):
    page.goto(static_url)
    page.wait_for_function("window.edmcgsViewer !== undefined")
    return page


def _decode_in_page(page, payload: bytes):
    """Decode msgpack bytes with the page's decoder; bytes come back as lists of ints."""
    return page.evaluate(
        """(b) => {
            const v = window.edmcgsViewer.unpack(new Uint8Array(b));
            return JSON.parse(JSON.stringify(v, (k, x) => x instanceof Uint8Array ? Array.from(x) : x));
        }""",
        list(payload),
    )


def _plain(value):
    """What the page should give back for a Python value: bytes as lists of ints."""
    if isinstance(value, bytes):
        return list(value)
    if isinstance(value, dict):
        return {k: _plain(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_plain(v) for v in value]
    return value


def test_msgpack_decoder_matches_python(viewer):
    frame = {
        "type": "frame", "seq": 70000, "dropped": 0, "t_us": 1_700_000_123_456_789, "t": 1.25,
        "anchor_us": 1_700_000_000_000_000, "events": 4_000_000_000, "render_ms": 12.5,
        "arrived_unix_us": None, "width": 346, "height": 260, "channels": 3, "format": "jpeg",
        "data": bytes(range(256)) * 300, "small": b"\x00\x01",
        "neg": [-1, -32, -33, -200, -40000, -3_000_000_000, -1_700_000_000_000_000],
        "uints": [0, 127, 128, 255, 256, 65535, 65536, 2**32 - 1, 2**32, 2**53 - 1],
        "flags": [True, False], "f32_nan_free": 0.1, "nested": {"a": [1, {"b": "ü€" * 20}]},
        "long_str": "x" * 70000, "many": list(range(20)), "big_map": {str(i): i for i in range(20)},
    }
    payload = msgpack.packb(frame, use_bin_type=True)
    assert _decode_in_page(viewer, payload) == _plain(frame)
    # single-precision floats, as other encoders send them
    f32 = msgpack.packb([0.5, -2.25], use_single_float=True)
    assert _decode_in_page(viewer, f32) == [0.5, -2.25]


@pytest.mark.parametrize("payload", [b"\x92\x01", b"\xc4\x05abc", b"\x01\x02", b"\xc1"])
def test_msgpack_decoder_rejects_bad_input(viewer, payload):
    message = viewer.evaluate(
        """(b) => { try { window.edmcgsViewer.unpack(new Uint8Array(b)); return null; }
                    catch (e) { return String(e.message); } }""",
        list(payload),
    )
    assert message is not None and message.startswith("msgpack:")


def _c2w(rot: Rotation, centre) -> list[float]:
    m = np.eye(4)
    m[:3, :3] = rot.as_matrix()
    m[:3, 3] = centre
    return m.reshape(-1).tolist()


def test_pose_at_matches_scipy_slerp(viewer):
    rng = np.random.default_rng(3)
    rots = Rotation.random(6, random_state=4)
    t_us = (1_700_000_000_000_000 + np.cumsum(rng.integers(10_000, 200_000, size=6))).tolist()
    centres = rng.normal(size=(6, 3))
    traj = {"t_us": t_us, "c2w": [_c2w(rots[i], centres[i]) for i in range(6)]}
    queries = [t_us[0] - 5, t_us[0], *np.sort(rng.uniform(t_us[0], t_us[-1], size=20)).tolist(),
               t_us[-1], t_us[-1] + 1_000_000]
    got = np.array(viewer.evaluate(
        "([traj, qs]) => qs.map((t) => window.edmcgsViewer.poseAt(traj, t))", [traj, queries]))
    slerp = Slerp(np.array(t_us, dtype=np.float64), rots)
    for q, pose in zip(queries, got, strict=True):
        tq = min(max(q, t_us[0]), t_us[-1])
        want = np.eye(4)
        want[:3, :3] = slerp([tq]).as_matrix()[0]
        want[:3, 3] = [np.interp(tq, t_us, centres[:, k]) for k in range(3)]
        np.testing.assert_allclose(pose.reshape(4, 4), want, atol=1e-9)
    assert viewer.evaluate("window.edmcgsViewer.poseAt({t_us: [], c2w: []}, 5)") is None


def test_quaternion_round_trip_covers_every_branch(viewer):
    # identity, 180° about each axis (the trace <= 0 branches), and random rotations
    rots = [np.eye(3), np.diag([1.0, -1, -1]), np.diag([-1.0, 1, -1]), np.diag([-1.0, -1, 1]),
            *Rotation.random(20, random_state=5).as_matrix()]
    got = viewer.evaluate(
        """(rs) => rs.map((R) => {
            const q = window.edmcgsViewer.quatFromRot(R);
            return [q, window.edmcgsViewer.rotFromQuat(q)];
        })""",
        [r.tolist() for r in rots],
    )
    for r, (q, back) in zip(rots, got, strict=True):
        assert math.isclose(np.linalg.norm(q), 1.0, rel_tol=1e-12)
        np.testing.assert_allclose(back, r, atol=1e-9)
        want = Rotation.from_matrix(r).as_quat()  # x, y, z, w
        assert abs(abs(np.dot(q, [want[3], *want[:3]])) - 1) < 1e-9


def test_orbit_turns_about_a_target_in_front_of_the_camera(viewer):
    base = _c2w(Rotation.from_euler("xyz", [0.3, -0.5, 0.2]), [0.4, -1.0, -3.0])
    depth = 2.5
    out = viewer.evaluate(
        """([base, depth]) => {
            const o = new window.edmcgsViewer.Orbit(base, depth);
            const start = o.c2w();
            o.rotate(0.7, -0.4);
            const turned = o.c2w();
            o.rotate(0, -10);  // pitch is clamped short of the pole
            const clamped = o.pitch;
            o.zoom(0.5);
            const zoomed = o.c2w();
            o.pan(0.3, -0.2);
            return {start, turned, clamped, zoomed, panned: o.c2w(), target: o.target};
        }""",
        [base, depth],
    )
    b = np.array(base).reshape(4, 4)
    target0 = b[:3, 3] + depth * b[:3, 2]
    np.testing.assert_allclose(np.array(out["start"]).reshape(4, 4), b, atol=1e-12)
    turned = np.array(out["turned"]).reshape(4, 4)
    r = turned[:3, :3]
    np.testing.assert_allclose(r @ r.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(r) == pytest.approx(1.0)
    assert not np.allclose(turned, b, atol=1e-3)
    # still looking at the target, from the same distance
    to_target = target0 - turned[:3, 3]
    assert np.linalg.norm(to_target) == pytest.approx(depth)
    np.testing.assert_allclose(to_target / depth, r[:, 2], atol=1e-12)
    # the yaw axis is the base camera's up: the camera's height along it is unchanged by yaw alone
    assert out["clamped"] == pytest.approx(-1.55)
    zoomed = np.array(out["zoomed"]).reshape(4, 4)
    assert np.linalg.norm(target0 - zoomed[:3, 3]) == pytest.approx(depth / 2)
    panned = np.array(out["panned"]).reshape(4, 4)
    np.testing.assert_allclose(panned[:3, :3], zoomed[:3, :3], atol=1e-12)  # a pan does not turn
    shift = panned[:3, 3] - zoomed[:3, 3]
    np.testing.assert_allclose(shift, -0.3 * zoomed[:3, 0] + 0.2 * zoomed[:3, 1], atol=1e-12)
    np.testing.assert_allclose(np.array(out["target"]) - target0, shift, atol=1e-12)


def test_page_reports_a_server_without_a_scene(viewer):
    banner = viewer.locator("#error")
    banner.wait_for(state="visible", timeout=5000)
    assert "cannot load the scene: 404" in viewer.locator("#error-text").inner_text()
    assert viewer.locator("#status").inner_text() == "no scene"
    assert json.loads(viewer.evaluate("JSON.stringify(window.edmcgsViewer.state.scene)")) is None


def test_page_hands_its_token_to_every_request(page, static_url):
    requests = []
    page.on("request", lambda r: requests.append((r.url, r.headers.get("authorization"))))
    page.goto(static_url + "?token=s3cret%2Fx")
    page.locator("#error").wait_for(state="visible", timeout=5000)
    by_name = {url.split("/")[-1].split("?")[0]: (url, auth) for url, auth in requests}
    assert by_name["viewer.js"][0].endswith("viewer.js?token=s3cret%2Fx")
    assert by_name["viewer.css"][0].endswith("viewer.css?token=s3cret%2Fx")
    scene_url, scene_auth = by_name["scene"]
    assert "token" not in scene_url and scene_auth == "Bearer s3cret/x"  # a header, not in the URL


def _nearest_reference(views: dict, pose: np.ndarray, far_deg: float, far_dist: float) -> dict:
    train = np.array(views["c2w"]).reshape(-1, 4, 4)
    d = np.linalg.norm(train[:, :3, 3] - pose[:3, 3], axis=1) / views["scale"]
    cos = np.clip(train[:, :3, 2] @ pose[:3, 2], -1, 1)
    a = np.degrees(np.arccos(cos))
    ratio = np.maximum(d / far_dist, a / far_deg)
    i = int(np.argmin(ratio))
    return {"distance": d[i], "angleDeg": a[i], "ratio": ratio[i], "far": bool(ratio[i] > 1)}


def _orbit_about(pose: np.ndarray, center: np.ndarray, degrees: float) -> np.ndarray:
    """``pose`` turned by ``degrees`` about the vertical axis through ``center``."""
    turn = Rotation.from_euler("y", degrees, degrees=True).as_matrix()
    out = np.eye(4)
    out[:3, :3] = turn @ pose[:3, :3]
    out[:3, 3] = center + turn @ (pose[:3, 3] - center)
    return out


def test_nearest_training_view_matches_numpy_and_draws_the_line_at_its_limits(viewer):
    far_deg, far_dist = viewer.evaluate(
        "[window.edmcgsViewer.FAR_ANGLE_DEG, window.edmcgsViewer.FAR_DISTANCE]")
    center = np.array([0.0, 0.0, 2.0])
    train = []
    for x in np.linspace(-0.1, 0.1, 9):  # a camera sliding along x, looking down +z at the centre
        m = np.eye(4)
        m[0, 3] = x
        train.append(m)
    views = {"center": center.tolist(), "scale": 2.0, "c2w": [m.reshape(-1).tolist() for m in train]}

    def nearest(pose: np.ndarray) -> dict:
        return viewer.evaluate("([v, p]) => window.edmcgsViewer.nearestTrainingView(v, p)",
                               [views, pose.reshape(-1).tolist()])

    rng = np.random.default_rng(7)
    poses = []
    for rot in Rotation.random(40, random_state=8):
        m = np.eye(4)
        m[:3, :3] = rot.as_matrix() if rng.random() < 0.5 else Rotation.from_rotvec(
            rng.normal(scale=0.2, size=3)).as_matrix()
        m[:3, 3] = rng.normal(scale=0.4, size=3)
        poses.append(m)
    for pose in poses:
        got, want = nearest(pose), _nearest_reference(views, pose, far_deg, far_dist)
        assert got["far"] == want["far"]
        for key in ("distance", "angleDeg", "ratio"):
            assert got[key] == pytest.approx(want[key], abs=1e-6), key

    at = train[4]
    assert nearest(at) == {"distance": 0, "angleDeg": 0, "ratio": 0, "far": False}
    rolled = at.copy()
    rolled[:3, :3] = at[:3, :3] @ Rotation.from_euler("z", 90, degrees=True).as_matrix()
    assert not nearest(rolled)["far"]  # a roll about the optical axis sees the same rays
    assert not nearest(_orbit_about(at, center, 0.8 * far_deg))["far"]
    assert nearest(_orbit_about(at, center, 1.25 * far_deg))["far"]
    back = at.copy()
    back[2, 3] -= 1.2 * far_dist * views["scale"]  # straight back, along the axis
    assert nearest(back)["far"]
    assert viewer.evaluate("window.edmcgsViewer.nearestTrainingView(null, [])") is None


def test_fit_asks_for_the_canvas_size_on_screen_within_the_limits(viewer):
    size = """([intr, limits, layer]) => {
        const v = window.edmcgsViewer;
        v.state.scene = {intrinsics: intr, limits};
        v.state.eventsLayer = layer;
        const main = document.querySelector('main');
        return [v.renderSize(), main.clientWidth - 16, main.clientHeight - 16];
    }"""
    intr = {"width": 173, "height": 130}
    big = {"max_width": 1920, "max_height": 1920}
    viewer.set_viewport_size({"width": 700, "height": 560})
    (w, h), avail_w, avail_h = viewer.evaluate(size, [intr, big, "off"])
    k = min(avail_w / 173, avail_h / 130)
    assert 1 < k < 4 and (w, h) == (int(173 * k), int(130 * k))  # the space on screen, its aspect kept
    (w2, h2), *_ = viewer.evaluate(size, [intr, big, "beside"])
    assert w2 < w and w2 <= (avail_w - 8) / 2 and abs(w2 / h2 - 173 / 130) < 0.02  # half the width
    assert viewer.evaluate(size, [intr, {"max_width": 200, "max_height": 1920}, "off"])[0] == [200, 150]
    viewer.set_viewport_size({"width": 3000, "height": 2000})
    assert viewer.evaluate(size, [intr, big, "off"])[0] == [4 * 173, 4 * 130]  # MAX_FIT_SCALE
    viewer.select_option("#scale", "0.5")
    assert viewer.evaluate(size, [intr, big, "off"])[0] == [86, 65]


def test_the_anchor_readout_says_what_an_online_anchor_is_and_whether_the_view_is_events_bounded(viewer):
    note = "(f) => window.edmcgsViewer.anchorNote(f)"
    assert viewer.evaluate(note, {"anchor": "checkpoint", "projected": False}) == ""
    assert viewer.evaluate(note, {}) == ""  # a server that does not say
    assert viewer.evaluate(note, {"anchor": "predicted", "projected": False}) == " (predicted)"
    assert viewer.evaluate(note, {"anchor": "corrected", "projected": True}) == " (corrected, events-bounded)"


def test_the_model_readout_says_which_model_renders_and_what_it_learnt(viewer):
    text = "([v, learning]) => window.edmcgsViewer.modelText(v, learning)"
    learnt = {"model": {"version": 3, "span_us": [0, 2_500_000], "anchors": 13, "steps": 600,
                        "heldout": {"psnr": 31.234}}}
    assert viewer.evaluate(text, [None, {}]) == "learning… (frame + events)"
    assert viewer.evaluate(text, [0, None]) == "checkpoint"  # a checkpoint given: no learner
    assert viewer.evaluate(text, [3, learnt]) == "learnt v3 (2.5 s, 13 anchors, step 600, held-out 31.2 dB)"
    assert viewer.evaluate(text, [4, learnt]) == "learnt v4"  # newer than what /scene said last


def test_a_typed_pose_reads_both_forms_with_the_quaternion_w_first(viewer):
    parse = "(text) => window.edmcgsViewer.parsePose(text)"
    rng = np.random.default_rng(11)
    for rot in Rotation.random(5, random_state=12):
        t = rng.normal(size=3).tolist()
        want = np.array(_c2w(rot, t)).reshape(4, 4)
        x, y, z, w = rot.as_quat().tolist()  # scipy: scalar last
        got = viewer.evaluate(parse, ",".join(map(repr, [*t, w, x, y, z])))
        np.testing.assert_allclose(np.array(got).reshape(4, 4), want, atol=1e-12)
        scaled = viewer.evaluate(parse, " ".join(map(repr, [*t, 2 * w, 2 * x, 2 * y, 2 * z])))
        np.testing.assert_allclose(np.array(scaled).reshape(4, 4), want, atol=1e-12)  # any norm
        # the 4x4 as 16 numbers, as a nested JSON array, and as numpy prints it
        for text in (",".join(map(repr, want.reshape(-1).tolist())), json.dumps(want.tolist()), str(want)):
            got = np.array(viewer.evaluate(parse, text)).reshape(4, 4)
            np.testing.assert_allclose(got, want, atol=1e-7)
            np.testing.assert_allclose(got[:3, :3] @ got[:3, :3].T, np.eye(3), atol=1e-12)  # orthonormal
    # a TUM line's quaternion read as w first is another rotation: the order matters
    rot = Rotation.from_euler("xyz", [0.4, -0.2, 0.9])
    x, y, z, w = rot.as_quat()
    tum_order = np.array(viewer.evaluate(parse, f"0,0,0,{x},{y},{z},{w}")).reshape(4, 4)
    assert not np.allclose(tum_order[:3, :3], rot.as_matrix(), atol=1e-3)


@pytest.mark.parametrize(("text", "message"), [
    ("", "type 16 numbers"),
    ("1,2,3,4,5", "got 5 numbers: give 16 (a 4x4 camera-to-world matrix, row-major) or 7 "
                  "(tx,ty,tz,qw,qx,qy,qz, the quaternion's w first)"),
    ("0,0,0,1,0,0,x", 'number 7, "x", is not a finite number'),
    ("0,0,0,1,0,0,Infinity", "is not a finite number"),
    ("0,0,0,0,0,0,0", "the quaternion (qw,qx,qy,qz) is zero"),
    ("2,0,0,0, 0,2,0,0, 0,0,2,0, 0,0,0,1", "not orthonormal"),
    ("1,0,0,0, 0,1,0,0, 0,0,-1,0, 0,0,0,1", "determinant −1"),
    ("1,0,0,0, 0,1,0,0, 0,0,1,0, 0,0,1,1", "bottom row must be 0,0,0,1"),
])
def test_a_typed_pose_that_is_wrong_says_what_is_wrong(viewer, text, message):
    error = viewer.evaluate("""(text) => {
        try { window.edmcgsViewer.parsePose(text); return null; } catch (err) { return err.message; }
    }""", text)
    assert error is not None and message in error, error


def _project(c2w: np.ndarray, intr: dict, width: int, height: int, points: np.ndarray) -> np.ndarray:
    """World points -> canvas coordinates of a render of ``width`` x ``height`` from ``c2w`` (pixel edges at
    integers, the intrinsics scaled as the server scales them)."""
    w2c = np.linalg.inv(c2w)
    p = points @ w2c[:3, :3].T + w2c[:3, 3]
    sx, sy = width / intr["width"], height / intr["height"]
    return np.stack([sx * (intr["fx"] * p[:, 0] / p[:, 2] + intr["cx"] + 0.5),
                     sy * (intr["fy"] * p[:, 1] / p[:, 2] + intr["cy"] + 0.5)], 1)


FRUSTUMS = "([v, p, k, w, h]) => window.edmcgsViewer.frustumSegments(v.c2w, v.scale, p, k, w, h)"


def test_frustums_are_the_training_cameras_projected_and_a_click_picks_one(viewer):
    intr = {"fx": 80.0, "fy": 80.0, "cx": 39.5, "cy": 29.5, "width": 80, "height": 60}
    center = np.array([0.0, 0.0, 3.0])
    train = [np.array(_c2w(Rotation.from_euler("y", a, degrees=True), [x, 0.0, 0.0])).reshape(4, 4)
             for x, a in ((-0.4, 8.0), (0.0, 0.0), (0.4, -8.0))]
    views = {"center": center.tolist(), "scale": 3.0, "c2w": [m.reshape(-1).tolist() for m in train]}
    # the view: stepped back and up from the middle camera, looking at the centre
    eye = np.array([0.3, -0.8, -1.5])
    zaxis = (center - eye) / np.linalg.norm(center - eye)
    xaxis = np.cross([0.0, 1.0, 0.0], zaxis)
    xaxis /= np.linalg.norm(xaxis)
    view = np.eye(4)
    view[:3, :3] = np.stack([xaxis, np.cross(zaxis, xaxis), zaxis], 1)
    view[:3, 3] = eye
    width, height = 320, 240
    got = viewer.evaluate(FRUSTUMS, [views, view.reshape(-1).tolist(), intr, width, height])
    depth = viewer.evaluate("window.edmcgsViewer.FRUSTUM_DEPTH") * views["scale"]
    assert [f["index"] for f in got] == [0, 1, 2]
    for f, m in zip(got, train, strict=True):
        segs = np.array(f["segs"])
        assert segs.shape == (10, 4)  # 4 edges from the apex, the base's 4 sides, the up mark's 2
        corners = np.array([[(u - intr["cx"]) / intr["fx"], (v - intr["cy"]) / intr["fy"], 1.0]
                            for u, v in ((-0.5, -0.5), (79.5, -0.5), (79.5, 59.5), (-0.5, 59.5))])
        world = m[:3, 3] + depth * corners @ m[:3, :3].T
        apex, base = _project(view, intr, width, height, np.vstack([m[:3, 3], world]))[[0]], \
            _project(view, intr, width, height, world)
        np.testing.assert_allclose(segs[:4, :2], np.repeat(apex, 4, 0), atol=1e-9)
        np.testing.assert_allclose(segs[:4, 2:], base, atol=1e-9)
        np.testing.assert_allclose(segs[4:8, :2], base, atol=1e-9)
        np.testing.assert_allclose(segs[4:8, 2:], np.roll(base, -1, 0), atol=1e-9)
        up = segs[8:, :].reshape(-1, 2)  # the up mark lies above the base's top edge on the screen
        assert (up[:, 1] <= np.maximum(base[0, 1], base[1, 1]) + 1e-9).all()

    # a click on the middle camera's base edge picks it; far from every line, none
    pick = "([f, x, y]) => window.edmcgsViewer.pickFrustum(f, x, y, 4)"
    x0, y0, x1, y1 = got[1]["segs"][6]
    assert viewer.evaluate(pick, [got, (x0 + x1) / 2 + 1, (y0 + y1) / 2 - 1]) == 1
    assert viewer.evaluate(pick, [got, -500, -500]) == -1

    # seen from a training camera itself: its own frustum is not drawn (its centre is the camera's);
    # a camera right beside it, turned away, is clipped at the near plane, never drawn from behind
    own = viewer.evaluate(FRUSTUMS, [views, train[1].reshape(-1).tolist(), intr, 80, 60])
    assert 1 not in [f["index"] for f in own]
    side = np.array(_c2w(Rotation.from_euler("y", 95, degrees=True), [0.0, 0.0, 0.5])).reshape(4, 4)
    one = {**views, "c2w": [side.reshape(-1).tolist()]}
    clipped = viewer.evaluate(FRUSTUMS, [one, train[1].reshape(-1).tolist(), intr, 80, 60])
    assert len(clipped) == 1 and all(np.isfinite(s).all() for s in clipped[0]["segs"])
    assert viewer.evaluate("window.edmcgsViewer.frustumSegments(null, 1, [], {}, 1, 1)") == []

    # the path: a segment between consecutive centres, clipped the same way
    path = np.array(viewer.evaluate(
        "([v, p, k, w, h]) => window.edmcgsViewer.pathSegments(v.c2w, v.scale, p, k, w, h)",
        [views, view.reshape(-1).tolist(), intr, width, height]))
    centres = _project(view, intr, width, height, np.array([m[:3, 3] for m in train]))
    np.testing.assert_allclose(path, np.hstack([centres[:-1], centres[1:]]), atol=1e-9)


def test_the_training_frames_cameras_are_the_trajectory_at_the_anchors(viewer):
    rots = Rotation.random(3, random_state=13)
    traj = {"t_us": [0, 100, 200], "c2w": [_c2w(rots[i], [0.1 * i, 0, 0]) for i in range(3)]}
    got = viewer.evaluate("([t, a]) => window.edmcgsViewer.anchorPoses(t, a)", [traj, [0, 100, 150]])
    want = viewer.evaluate("([t, a]) => a.map((x) => window.edmcgsViewer.poseAt(t, x))",
                           [traj, [0, 100, 150]])
    assert got == want
    np.testing.assert_allclose(got[1], traj["c2w"][1], atol=1e-12)
    assert viewer.evaluate("window.edmcgsViewer.anchorPoses(null, [1, 2])") == []


def test_the_depth_readout(viewer):
    text = "([r, m]) => window.edmcgsViewer.depthText(r, m)"
    assert viewer.evaluate(text, [{"near": 1.2345, "far": 12.5}, "depth"]) == "1.234–12.5 m"
    assert viewer.evaluate(text, [None, "depth"]) == "nothing in view"
    assert viewer.evaluate(text, [None, "rgb"]) == "–"
