"""The viewer's events layer, far-view notice and screenshot button in a real headless Chromium against
the real service (edmcgs-serve in a subprocess, a token required)."""

from __future__ import annotations

import base64
import io
import re

import numpy as np
from PIL import Image
from scipy.spatial.transform import Rotation

from edmcgs import protocol
from edmcgs.clients.client import Client

FRAMES = "Number(document.getElementById('frames').textContent)"
IDLE = "!edmcgsViewer.state.rendering && !edmcgsViewer.state.viewDirty"
EVENTS_SHOWN = ("edmcgsViewer.state.events !== null && !edmcgsViewer.state.eventsFetching && "
                "edmcgsViewer.state.events.tUs === edmcgsViewer.state.tUs")


def _pixels(page, selector: str) -> np.ndarray:
    """A canvas' own pixels, uint8 [H, W, 3]."""
    url = page.evaluate(f"document.querySelector({selector!r}).toDataURL('image/png')")
    return np.asarray(Image.open(io.BytesIO(base64.b64decode(url.split(",", 1)[1]))).convert("RGB"))


def _paused(page, served):
    page.goto(f"{served.url}/?token={served.token}")
    page.wait_for_function(f"{FRAMES} >= 3", timeout=30_000)
    page.click("#play")
    page.wait_for_function(f"{IDLE} && document.getElementById('status').textContent === 'paused' && "
                           "edmcgsViewer.state.tUs !== null", timeout=20_000)


def _between_anchors(page) -> None:
    """The paused still moved to halfway between two anchors (at an anchor the window is empty)."""
    t_us = page.evaluate("""() => {
        const s = edmcgsViewer.state.scene, a = s.anchors_us, slider = document.getElementById('slider');
        slider.value = String(Math.round(((a[1] + a[2]) / 2 - s.t_start_us) / 1000));
        slider.dispatchEvent(new Event('input'));
        return s.t_start_us + Number(slider.value) * 1000;
    }""")
    page.wait_for_function(f"{IDLE} && edmcgsViewer.state.tUs === {t_us}", timeout=20_000)


def _event_map(served, t_us: int) -> np.ndarray:
    with Client(served.url, served.token) as client:
        emap, meta = client.events(t_us=t_us)
    assert meta.t_us == t_us and meta.events > 0
    return emap


def _nearest(emap: np.ndarray, height: int, width: int) -> np.ndarray:
    """The event map at another size, nearest neighbour (sample at each output pixel's centre)."""
    ys = ((np.arange(height) + 0.5) * emap.shape[0] / height).astype(int)
    xs = ((np.arange(width) + 0.5) * emap.shape[1] / width).astype(int)
    return emap[ys[:, None], xs[None, :]]


def test_events_layer_follows_the_live_stream(page, served):
    page.goto(f"{served.url}/?token={served.token}")
    page.wait_for_function(f"{FRAMES} >= 3", timeout=30_000)
    page.keyboard.press("e")
    assert page.locator("#events-layer").input_value() == "over"
    seen = set()
    for _ in range(3):  # the map of each new frame's window, a moment after the frame
        page.wait_for_function(f"edmcgsViewer.state.events !== null && "
                               f"![{','.join(map(str, seen)) or ''}].includes(edmcgsViewer.state.events.tUs)",
                               timeout=10_000)
        seen.add(page.evaluate("edmcgsViewer.state.events.tUs"))
    assert len(seen) == 3 and page.locator("#status").inner_text() == "live"
    # the canvas and the map it shows, read in one turn of the page's event loop (frames keep coming)
    url, on_map, off_map = page.evaluate(f"""() => {{
        const px = edmcgsViewer.state.events.pixels.data;
        let on = 0, off = 0;
        for (let i = 0; i < px.length; i += 4) {{
            if (px[i + 3] === 0) continue;
            if (px[i + 2] === {protocol.EVENT_ON_RGB[2]}) on++; else off++;
        }}
        return [document.getElementById('view').toDataURL('image/png'), on, off];
    }}""")
    view = np.asarray(Image.open(io.BytesIO(base64.b64decode(url.split(",", 1)[1]))).convert("RGB"))
    on, off = (view == protocol.EVENT_ON_RGB).all(-1).sum(), (view == protocol.EVENT_OFF_RGB).all(-1).sum()
    assert (on > 0) == (on_map > 0) and (off > 0) == (off_map > 0), (on, off, on_map, off_map)
    assert on >= on_map and off >= off_map  # the canvas is larger: each sensor pixel takes 1 or 2 pixels
    assert page.errors == [] and page.locator("#error").is_hidden()


def test_events_layer_shows_the_windows_events_and_the_toggle_hides_them(page, served, tmp_path):
    _paused(page, served)
    _between_anchors(page)
    render = _pixels(page, "#view")
    box = page.locator("#view").bounding_box()

    def screen(emap_shape) -> np.ndarray:
        """The page as a person sees it, at each sensor pixel's centre on the screen, int [H, W, 3]."""
        path = tmp_path / "shot.png"
        page.screenshot(path=str(path))
        shot = np.asarray(Image.open(path).convert("RGB")).astype(np.int64)
        h, w = emap_shape
        ys = np.floor(box["y"] + (np.arange(h) + 0.5) * box["height"] / h).astype(int)
        xs = np.floor(box["x"] + (np.arange(w) + 0.5) * box["width"] / w).astype(int)
        return shot[ys[:, None], xs[None, :]]

    page.select_option("#events-layer", "over")
    page.wait_for_function(EVENTS_SHOWN, timeout=10_000)
    t_us = page.evaluate("edmcgsViewer.state.tUs")
    emap = _event_map(served, t_us)

    # the canvas: each sensor pixel a block of the event colour where the window's sum is non-zero,
    # the render untouched elsewhere
    over = _pixels(page, "#view")
    up = _nearest(emap, *over.shape[:2])
    assert (over[up > 0] == protocol.EVENT_ON_RGB).all() and (over[up < 0] == protocol.EVENT_OFF_RGB).all()
    np.testing.assert_array_equal(over[up == 0], render[up == 0])
    seen = screen(emap.shape)

    # the toggle: off, and the render is back as it was, on the canvas and on the screen
    page.keyboard.press("e")
    assert page.locator("#events-layer").input_value() == "off"
    np.testing.assert_array_equal(_pixels(page, "#view"), render)
    hidden = screen(emap.shape)

    # on the screen, the layer turned the pixels of the window's events blue (ON won) or red (OFF won),
    # and left the others as the render shows them (the browser scales the canvas up smoothly: only a
    # neighbour of an event pixel may take a tint)
    def near(mask: np.ndarray) -> np.ndarray:
        """Where the pixel or one of its 8 neighbours is in ``mask``."""
        padded, out = np.pad(mask, 1), np.zeros_like(mask)
        for dy in range(3):
            for dx in range(3):
                out |= padded[dy:dy + mask.shape[0], dx:dx + mask.shape[1]]
        return out

    gain = seen - hidden
    blue, red = gain[..., 2] - gain[..., 0], gain[..., 0] - gain[..., 2]
    assert (blue[(emap > 0) & ~near(emap < 0)] > 40).mean() > 0.98
    assert (red[(emap < 0) & ~near(emap > 0)] > 40).mean() > 0.98
    assert (blue[emap > 0] > 0).mean() > 0.95 and (red[emap < 0] > 0).mean() > 0.95
    busy = near(emap != 0)
    assert (~busy).sum() > 100
    assert (np.abs(gain[~busy]).max(-1) < 10).mean() > 0.99
    on, off = np.array(protocol.EVENT_ON_RGB), np.array(protocol.EVENT_OFF_RGB)
    assert np.abs(seen[emap > 0] - on).max(-1).mean() < np.abs(hidden[emap > 0] - on).max(-1).mean() - 60
    assert np.abs(seen[emap < 0] - off).max(-1).mean() < np.abs(hidden[emap < 0] - off).max(-1).mean() - 60

    # beside: the render alone, and the events on white next to it
    page.select_option("#events-layer", "beside")
    page.wait_for_function(f"{IDLE} && {EVENTS_SHOWN}", timeout=10_000)
    side = page.locator("#events-view")
    assert side.is_visible()
    assert side.bounding_box()["x"] >= page.locator("#view").bounding_box()["x"] + 10
    beside = _pixels(page, "#events-view")
    t_us = page.evaluate("edmcgsViewer.state.tUs")
    up = _nearest(_event_map(served, t_us), *beside.shape[:2])
    assert (beside[up > 0] == protocol.EVENT_ON_RGB).all()
    assert (beside[up < 0] == protocol.EVENT_OFF_RGB).all()
    assert (beside[up == 0] == 255).all()
    view = _pixels(page, "#view")  # the render itself carries no events: the camera's size, no event colour
    assert view.shape == over.shape and not (view == protocol.EVENT_ON_RGB).all(-1).any()
    page.select_option("#events-layer", "off")
    assert side.is_hidden()
    assert page.errors == []


def test_far_view_notice_after_an_orbit_away_and_not_at_a_training_view(page, served):
    page.goto(f"{served.url}/?token={served.token}")
    page.wait_for_function(f"{FRAMES} >= 3", timeout=30_000)
    notice = page.locator("#far-notice")
    assert notice.is_hidden()  # the event camera's own pose

    # a small orbit stays near the training views
    box = page.locator("#view").bounding_box()
    x, y = box["x"] + box["width"] / 2, box["y"] + box["height"] / 2
    page.mouse.move(x, y)
    page.mouse.down()
    page.mouse.move(x + 6, y)
    page.mouse.up()
    page.wait_for_function("edmcgsViewer.currentPose() !== null && !edmcgsViewer.state.viewDirty")
    near = page.evaluate("edmcgsViewer.nearestTrainingView(edmcgsViewer.state.scene.training_views, "
                         "edmcgsViewer.currentPose())")
    assert 0 < near["angleDeg"] < 5 and not near["far"]
    assert notice.is_hidden()

    # a long drag turns the camera about 50 degrees about the scene: far, and the notice says why
    page.mouse.move(x, y)
    page.mouse.down()
    for k in range(1, 11):
        page.mouse.move(x + 12 * k, y)
    page.mouse.up()
    notice.wait_for(state="visible", timeout=5000)
    text = page.locator("#far-text").inner_text()
    assert "far from every training view" in text
    assert re.search(r"nearest is \d+° turned", text) and "no camera saw" in text, text

    # another training view than the event camera's at this time: near, no notice
    page.evaluate("""() => {
        const v = edmcgsViewer.state.scene.training_views;
        edmcgsViewer.state.orbit = new edmcgsViewer.Orbit(v.c2w[v.c2w.length - 1], 1.0);
    }""")
    page.mouse.move(x, y)
    page.mouse.down()
    page.mouse.move(x + 1, y)  # a pixel's orbit: a view change the page reacts to
    page.mouse.up()
    page.wait_for_function("!edmcgsViewer.state.viewDirty")
    notice.wait_for(state="hidden", timeout=5000)

    # and the reset goes back to the event camera: no notice
    page.mouse.move(x, y)
    page.mouse.down()
    for k in range(1, 11):
        page.mouse.move(x, y + 15 * k)
    page.mouse.up()
    notice.wait_for(state="visible", timeout=5000)
    page.click("#reset")
    notice.wait_for(state="hidden", timeout=5000)
    assert page.errors == []


def test_screenshot_button_downloads_the_view_as_png(page, served):
    _paused(page, served)
    with page.expect_download(timeout=10_000) as info:
        page.click("#screenshot")
    download = info.value
    seconds = page.evaluate("(edmcgsViewer.state.tUs - edmcgsViewer.state.scene.t_start_us) / 1e6")
    assert download.suggested_filename == f"edmcgs-t{seconds:.3f}s.png"
    data = open(download.path(), "rb").read()
    assert data.startswith(b"\x89PNG\r\n\x1a\n")
    shot = np.asarray(Image.open(io.BytesIO(data)).convert("RGB"))
    np.testing.assert_array_equal(shot, _pixels(page, "#view"))  # exactly the view on screen

    # beside: the render and the events side by side in one picture
    page.select_option("#events-layer", "beside")
    page.wait_for_function(f"{IDLE} && {EVENTS_SHOWN}", timeout=10_000)
    with page.expect_download(timeout=10_000) as info:
        page.click("#screenshot")
    both = np.asarray(Image.open(info.value.path()).convert("RGB"))
    view, side = _pixels(page, "#view"), _pixels(page, "#events-view")
    assert both.shape == (view.shape[0], view.shape[1] + side.shape[1], 3)
    np.testing.assert_array_equal(both[:, :view.shape[1]], view)
    np.testing.assert_array_equal(both[:, view.shape[1]:], side)
    assert page.errors == []


def test_ply_button_downloads_the_gaussians_at_the_time_on_screen(page, served):
    _paused(page, served)
    with page.expect_download(timeout=20_000) as info:
        page.click("#ply")
    download = info.value
    t_us = page.evaluate("edmcgsViewer.state.tUs")
    seconds = page.evaluate("(edmcgsViewer.state.tUs - edmcgsViewer.state.scene.t_start_us) / 1e6")
    assert download.suggested_filename == f"edmcgs-t{seconds:.3f}s.ply"
    data = open(download.path(), "rb").read()
    with Client(served.url, served.token) as client:
        assert data == client.ply(t_us=t_us)  # what GET /ply gives for that time, byte for byte
    assert data.startswith(b"ply\n") and page.errors == []


def _page_point(page, x: float, y: float) -> tuple[float, float]:
    """Canvas coordinates of #view -> the page's (the canvas keeps its aspect ratio in its box)."""
    box = page.locator("#view").bounding_box()
    w, h = page.evaluate("[document.getElementById('view').width, document.getElementById('view').height]")
    k = min(box["width"] / w, box["height"] / h)
    return box["x"] + (box["width"] - w * k) / 2 + x * k, box["y"] + (box["height"] - h * k) / 2 + y * k


def _segment_mask(frustums: list, shape: tuple[int, int], reach: float) -> np.ndarray:
    """The canvas pixels whose centre lies within ``reach`` of a frustum's segment."""
    h, w = shape
    ys, xs = np.mgrid[0:h, 0:w] + 0.5
    mask = np.zeros(shape, bool)
    for f in frustums:
        for x0, y0, x1, y1 in f["segs"]:
            dx, dy = x1 - x0, y1 - y0
            a = np.clip(((xs - x0) * dx + (ys - y0) * dy) / max(dx * dx + dy * dy, 1e-12), 0, 1)
            mask |= np.hypot(xs - (x0 + a * dx), ys - (y0 + a * dy)) <= reach
    return mask


def test_training_cameras_are_drawn_as_frustums_and_a_click_goes_to_one(page, served):
    _paused(page, served)
    # the event camera slides along its own x axis: every training camera is beside it, none in front;
    # zoomed out (the wheel backs the free camera away), they come into view
    x, y = _page_point(page, *page.evaluate("[document.getElementById('view').width / 2, "
                                            "document.getElementById('view').height / 2]"))
    before = page.evaluate(FRAMES)
    page.mouse.move(x, y)
    page.mouse.wheel(0, 900)
    page.wait_for_function(f"{IDLE} && {FRAMES} > {before} && edmcgsViewer.currentPose() !== null")
    assert not page.locator("#cameras").is_checked() and page.evaluate("edmcgsViewer.state.frustums") == []
    plain = _pixels(page, "#view").astype(int)

    page.keyboard.press("c")
    assert page.locator("#cameras").is_checked()
    frustums = page.evaluate("edmcgsViewer.state.frustums")
    cameras = page.evaluate("edmcgsViewer.state.cameraPoses")
    assert len(cameras) == 9 and len(frustums) == 9 and page.evaluate(  # the 9 training frames
        "JSON.stringify(edmcgsViewer.state.imagePose) === JSON.stringify(edmcgsViewer.currentPose())")
    drawn = _pixels(page, "#view").astype(int)
    changed = np.abs(drawn - plain).max(-1) > 40
    assert changed.sum() > 30  # the lines are there ...
    path = page.evaluate("""() => {
        const s = edmcgsViewer.state, v = s.scene.training_views, c = document.getElementById('view');
        return edmcgsViewer.pathSegments(v.c2w, v.scale, s.imagePose, s.scene.intrinsics, c.width, c.height);
    }""")
    lines = _segment_mask([*frustums, {"segs": path}], changed.shape, 2.5)
    assert not (changed & ~lines).any()  # ... and only there
    assert (drawn[changed][:, 0] > drawn[changed][:, 2] + 60).mean() > 0.8  # orange

    # the pointer on a frustum's base edge: the pointer cursor, and a click goes to that camera's pose
    f = frustums[len(frustums) // 2]
    x0, y0, x1, y1 = f["segs"][5]
    cx, cy = (x0 + x1) / 2, (y0 + y1) / 2
    px, py = _page_point(page, cx, cy)
    page.mouse.move(px, py)
    page.wait_for_function("document.getElementById('view').style.cursor === 'pointer'", timeout=5000)
    picked = page.evaluate(f"edmcgsViewer.pickFrustum(edmcgsViewer.state.frustums, {cx}, {cy}, 6)")
    assert picked >= 0 and _segment_mask([frustums[[g["index"] for g in frustums].index(picked)]],
                                         changed.shape, 6)[int(cy), int(cx)]
    before = page.evaluate(FRAMES)
    page.mouse.click(px, py)
    page.wait_for_function(f"{IDLE} && {FRAMES} > {before}")
    pose = page.evaluate("edmcgsViewer.currentPose()")
    np.testing.assert_allclose(pose, cameras[picked], atol=1e-9)
    # from a training camera the others lie beside it: none drawn, the canvas is the server's render
    assert page.evaluate("edmcgsViewer.state.frustums") == []
    shot = _pixels(page, "#view")
    with Client(served.url, served.token) as client:
        png, _ = client.render(t_us=page.evaluate("edmcgsViewer.state.tUs"), pose=pose, width=shot.shape[1],
                               height=shot.shape[0], format="png")
    reference = np.asarray(Image.open(io.BytesIO(png)).convert("RGB"))
    assert np.abs(shot.astype(int) - reference).mean() < 3.0  # JPEG on the wire
    page.keyboard.press("c")
    assert not page.locator("#cameras").is_checked() and page.errors == []


def test_depth_and_alpha_modes_show_the_servers_grey_renders(page, served):
    _paused(page, served)
    t_us = page.evaluate("edmcgsViewer.state.tUs")
    assert page.locator("#depth-range").is_hidden()
    with Client(served.url, served.token) as client:
        for mode in ("depth", "alpha"):
            page.select_option("#render-mode", mode)
            page.wait_for_function(f"{IDLE} && edmcgsViewer.state.imageMode === '{mode}'")
            shown = _pixels(page, "#view").astype(int)
            assert np.ptp(shown, axis=-1).max() <= 6  # grey (JPEG's chroma aside)
            grey, meta = client.render(t_us=t_us, width=shown.shape[1], height=shown.shape[0], mode=mode,
                                       format="png")
            reference = np.asarray(Image.open(io.BytesIO(grey))).astype(int)
            assert reference.ndim == 2 and reference.std() > 10
            assert np.abs(shown[..., 0] - reference).mean() < 3.0
            if mode == "depth":
                assert page.locator("#depth-range").is_visible()
                assert page.evaluate("edmcgsViewer.state.depthRange") == {"near": meta.depth_near,
                                                                          "far": meta.depth_far}
                readout = page.evaluate("([near, far]) => edmcgsViewer.depthText({near, far}, 'depth')",
                                        [meta.depth_near, meta.depth_far])
                assert page.locator("#depth-range").inner_text() == readout
            else:
                assert page.locator("#depth-range").is_hidden()
    # live: the stream's subscription carries the mode
    page.select_option("#render-mode", "depth")
    page.click("#play")
    before = page.evaluate(FRAMES)
    page.wait_for_function(f"{FRAMES} >= {before + 3} && /m$/.test(document.getElementById('depth-range')"
                           ".textContent)", timeout=20_000)
    assert np.ptp(_pixels(page, "#view").astype(int), axis=-1).max() <= 6
    assert page.errors == []


def test_a_typed_pose_is_rendered_and_a_wrong_one_is_refused(page, served):
    _paused(page, served)
    hint = page.locator(".hint").inner_text()
    assert "w first" in hint and "qw,qx,qy,qz" in hint and "qx qy qz qw" in hint  # the order, stated
    t_us = page.evaluate("edmcgsViewer.state.tUs")
    own = np.array(page.evaluate(f"edmcgsViewer.poseAt(edmcgsViewer.state.scene.trajectory, {t_us})"))
    own = own.reshape(4, 4)
    turn = Rotation.from_euler("yx", [6.0, -3.0], degrees=True)
    want = np.eye(4)
    want[:3, :3] = turn.as_matrix() @ own[:3, :3]
    want[:3, 3] = own[:3, 3] + [0.04, -0.02, 0.01]
    qx, qy, qz, qw = Rotation.from_matrix(want[:3, :3]).as_quat().tolist()
    before = page.evaluate(FRAMES)
    page.fill("#pose-input", ", ".join(map(repr, [*want[:3, 3].tolist(), qw, qx, qy, qz])))
    page.press("#pose-input", "Enter")
    page.wait_for_function(f"{IDLE} && {FRAMES} > {before}")
    pose = np.array(page.evaluate("edmcgsViewer.currentPose()")).reshape(4, 4)
    np.testing.assert_allclose(pose, want, atol=1e-9)
    shot = _pixels(page, "#view")
    with Client(served.url, served.token) as client:
        png, _ = client.render(t_us=t_us, pose=want, width=shot.shape[1], height=shot.shape[0], format="png")
    assert np.abs(shot.astype(int) - np.asarray(Image.open(io.BytesIO(png)).convert("RGB"))).mean() < 3.0

    # the same pose as the 4x4, pasted as numpy prints it
    page.click("#reset")
    page.wait_for_function(f"{IDLE} && edmcgsViewer.currentPose() === null")
    page.fill("#pose-input", str(want))
    page.click("#pose-form button")
    page.wait_for_function("edmcgsViewer.currentPose() !== null")
    np.testing.assert_allclose(page.evaluate("edmcgsViewer.currentPose()"), want.reshape(-1), atol=1e-7)

    # wrong: a clear message, the field marked, the view unchanged
    for text, message in (("1, 2, 3", "got 3 numbers: give 16"),
                          ("0,0,0, 0,0,0,0", "quaternion (qw,qx,qy,qz) is zero"),
                          ("2,0,0,0,0,2,0,0,0,0,2,0,0,0,0,1", "not orthonormal")):
        page.fill("#pose-input", text)
        page.click("#pose-form button")
        page.locator("#error").wait_for(state="visible", timeout=5000)
        shown = page.locator("#error-text").inner_text()
        assert shown.startswith("pose: ") and message in shown, shown
        assert page.locator("#pose-input").get_attribute("aria-invalid") == "true"
        np.testing.assert_allclose(page.evaluate("edmcgsViewer.currentPose()"), want.reshape(-1), atol=1e-7)
        page.locator("#error-close").click()
    page.fill("#pose-input", "0,0,0,1,0,0,0")
    assert page.locator("#pose-input").get_attribute("aria-invalid") is None  # typing clears the mark
    assert page.errors == []
