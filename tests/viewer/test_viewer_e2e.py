"""The browser viewer in a real headless Chromium against the real service (edmcgs-serve in a
subprocess, a token required), and ``edmcgs export`` against the same service."""

from __future__ import annotations

import base64
import io

import numpy as np
import pytest
from PIL import Image, ImageSequence

from edmcgs.clients.client import Client
from edmcgs.clients.export import main as export_main
from tests.support.viewer import MAX_SIZE, VIEW_H, VIEW_W

FRAMES = "Number(document.getElementById('frames').textContent)"
IDLE = "!edmcgsViewer.state.rendering && !edmcgsViewer.state.viewDirty"


def _canvas(page) -> np.ndarray:
    """The canvas' own pixels (at the frame's resolution), uint8 [H, W, 3]."""
    url = page.evaluate("document.getElementById('view').toDataURL('image/png')")
    data = base64.b64decode(url.split(",", 1)[1])
    return np.asarray(Image.open(io.BytesIO(data)).convert("RGB"))


def _reference(served, t_us: int, pose, width: int = VIEW_W, height: int = VIEW_H) -> np.ndarray:
    """The same view from the Python client, lossless."""
    with Client(served.url, served.token) as client:
        png, meta = client.render(t_us=t_us, pose=pose, width=width, height=height, format="png")
    assert meta.t_us == t_us
    return np.asarray(Image.open(io.BytesIO(png)).convert("RGB"))


def _mean_abs(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.abs(a.astype(np.float64) - b.astype(np.float64)).mean())


def _open(page, served):
    page.goto(f"{served.url}/?token={served.token}")
    page.wait_for_function(f"{FRAMES} >= 5", timeout=30_000)


def test_viewer_streams_orbits_and_shows_the_scene(page, served, tmp_path):
    _open(page, served)
    assert page.locator("#status").inner_text() == "live"
    assert page.locator("#error").is_hidden()
    anchors = page.locator("#ticks span")
    assert anchors.count() == 9  # anchors every 0.25 s over 2 s, marked on the slider

    # the readouts are live: fps > 0, the latencies and the frame age measured, frames and time moving
    page.wait_for_function("parseFloat(document.getElementById('fps').textContent) > 0", timeout=10_000)
    page.wait_for_function("/^\\d+ ms$/.test(document.getElementById('latency').textContent)", timeout=10_000)
    for readout in ("event-latency", "frame-age"):
        page.wait_for_function(f"/^-?\\d+ ms$/.test(document.getElementById('{readout}').textContent)",
                               timeout=10_000)
    frames, shown_t = page.evaluate(f"[{FRAMES}, document.getElementById('time').textContent]")
    page.wait_for_function(f"{FRAMES} >= {frames + 5} && document.getElementById('time').textContent "
                           f"!== {shown_t!r}", timeout=20_000)
    # refreshed every 250 ms: still a rate, above 0 once frames flow (a starved machine can stall the stream
    # for a second, which the readout rightly shows as 0.0)
    page.wait_for_timeout(600)
    page.wait_for_function("/^\\d+\\.\\d$/.test(document.getElementById('fps').textContent) && "
                           "parseFloat(document.getElementById('fps').textContent) > 0", timeout=10_000)

    # pause: a still at the slider's time from the event camera's pose, exactly what the server renders
    page.click("#play")
    assert page.locator("#play").inner_text() == "Play"
    page.wait_for_function(f"{IDLE} && document.getElementById('status').textContent === 'paused'")
    t_us = page.evaluate("edmcgsViewer.state.tUs")
    still = _canvas(page)
    # "fit": the canvas' size on screen (several times the camera's), capped by the server's limit
    fit = (round(MAX_SIZE * VIEW_H / VIEW_W), MAX_SIZE)
    assert still.shape == (*fit, 3)
    assert _mean_abs(still, _reference(served, t_us, None, fit[1], fit[0])) < 3.0  # JPEG on the wire

    # orbit with the mouse: the pose changes, and the canvas shows the server's render of that pose
    box = page.locator("#view").bounding_box()
    x, y = box["x"] + box["width"] / 2, box["y"] + box["height"] / 2
    before = page.evaluate(FRAMES)
    page.mouse.move(x, y)
    page.mouse.down()
    for k in range(1, 11):
        page.mouse.move(x + 12 * k, y + 4 * k)
    page.mouse.up()
    page.wait_for_function(f"{IDLE} && {FRAMES} > {before}")
    pose = page.evaluate("edmcgsViewer.currentPose()")
    assert pose is not None
    # the readouts refresh on a 250 ms timer: the frame can arrive before the next tick
    page.wait_for_function("document.getElementById('pose').textContent.startsWith('[')", timeout=5_000)
    base = np.array(page.evaluate(f"edmcgsViewer.poseAt(edmcgsViewer.state.scene.trajectory, {t_us})"))
    pose = np.array(pose)
    assert np.abs(pose - base).max() > 0.1
    rot = pose.reshape(4, 4)[:3, :3]
    np.testing.assert_allclose(rot @ rot.T, np.eye(3), atol=1e-9)
    assert page.evaluate("edmcgsViewer.state.tUs") == t_us  # the time stayed put
    orbited = _canvas(page)
    assert _mean_abs(orbited, still) > 2.0  # a different view
    reference = _reference(served, t_us, pose.tolist(), fit[1], fit[0])
    assert _mean_abs(orbited, reference) < 3.0

    # the page as a person sees it: the canvas area holds the scene (not blank, its colours)
    shot_path = tmp_path / "viewer.png"
    page.screenshot(path=str(shot_path))
    shot = np.asarray(Image.open(shot_path).convert("RGB")).astype(np.float64)
    crop = shot[round(box["y"]) + 2:round(box["y"] + box["height"]) - 2,
                round(box["x"]) + 2:round(box["x"] + box["width"]) - 2]
    assert crop.std() > 10, "the canvas area of the screenshot is flat"
    scaled = np.asarray(Image.fromarray(reference).resize((crop.shape[1], crop.shape[0]), Image.BILINEAR))
    # an orbit this far is far from every training view: the notice lies over the top of the view
    notice = page.locator("#far-notice")
    assert notice.is_visible() and page.locator("#view").bounding_box() == box  # the view did not move
    below = round(notice.bounding_box()["y"] + notice.bounding_box()["height"] - box["y"]) + 2
    crop, scaled = crop[below:], scaled[below:]
    assert _mean_abs(crop, scaled) < 8.0
    np.testing.assert_allclose(crop.reshape(-1, 3).mean(0), scaled.reshape(-1, 3).mean(0), atol=4.0)

    # back to the event camera, then live again
    page.click("#reset")
    page.wait_for_function(f"{IDLE} && document.getElementById('pose').textContent === 'event camera'")
    page.click("#play")
    before = page.evaluate(FRAMES)
    page.wait_for_function(f"{FRAMES} >= {before + 3} && document.getElementById('status').textContent "
                           "=== 'live'", timeout=20_000)
    assert page.errors == []


def test_viewer_shows_what_the_server_refuses(page, served):
    _open(page, served)
    # 2x of 160x120 passes the server's cap of 200 px: the stream answers with an error message
    page.select_option("#scale", "2")
    page.locator("#error").wait_for(state="visible", timeout=10_000)
    text = page.locator("#error-text").inner_text()
    assert text.startswith("stream: ") and "width" in text and str(MAX_SIZE) in text, text
    # ... and the stream goes on with the subscription in force before
    before = page.evaluate(FRAMES)
    page.wait_for_function(f"{FRAMES} >= {before + 3}", timeout=20_000)
    # paused, the same size is refused by GET /render, with the status
    page.click("#play")
    page.locator("#error-close").click()
    page.select_option("#scale", "2")
    page.locator("#error").wait_for(state="visible", timeout=10_000)
    text = page.locator("#error-text").inner_text()
    assert text.startswith("render: 422") and "width" in text, text
    assert [e for e in page.errors if "422" not in e] == []  # the browser logs the failed request


def test_export_gif_from_the_running_service(served, tmp_path, capsys):
    out = tmp_path / "sweep.gif"
    rc = export_main([str(out), "--url", served.url, "--token", served.token, "--t0", "0.25", "--t1", "0.75",
                      "--fps", "10", "--quiet"])
    assert rc == 0, capsys.readouterr().err
    assert "wrote 6 frames" in capsys.readouterr().out
    with Image.open(out) as gif:
        assert gif.n_frames == 6 and gif.size == (VIEW_W, VIEW_H)
        frames = [np.asarray(f.convert("RGB")).astype(np.float64) for f in ImageSequence.Iterator(gif)]
    assert all(f.std() > 5 for f in frames)
    # the first frame is the server's render at t0 (up to the GIF palette)
    with Client(served.url, served.token) as client:
        first, _meta = client.render(t=0.25, format="msgpack")
    assert _mean_abs(frames[0], first) < 6.0
    assert sorted(p.name for p in tmp_path.iterdir()) == ["sweep.gif"]  # no temporary left behind


def test_export_mp4_at_a_requested_size(served, tmp_path):
    import imageio_ffmpeg  # the dev extra installs it

    out = tmp_path / "sweep.mp4"
    rc = export_main([str(out), "--url", served.url, "--token", served.token, "--t0", "1", "--t1", "1.3",
                      "--fps", "10", "--width", "80", "--height", "60", "--quiet"])
    assert rc == 0
    reader = imageio_ffmpeg.read_frames(str(out))
    meta = next(reader)
    assert meta["size"] == (80, 60)
    assert sum(1 for _ in reader) == 4


@pytest.mark.parametrize(("args", "message"), [
    (["--t0", "5", "--t1", "6"], "416"),                  # past the scene's end: the valid range is stated
    (["--width", "400"], "width"),                        # past the server's size cap
    (["--pose", "1,2,3"], "pose must have 16"),           # malformed before anything is sent
])
def test_export_reports_what_goes_wrong(served, tmp_path, capsys, args, message):
    out = tmp_path / "sweep.gif"
    rc = export_main([str(out), "--url", served.url, "--token", served.token, "--quiet", *args])
    err = capsys.readouterr().err
    assert rc == 1 and err.startswith("edmcgs export: error: ") and message in err, err
    assert not out.exists() and list(tmp_path.iterdir()) == []


def test_export_without_the_token_is_refused(served, tmp_path, capsys):
    rc = export_main([str(tmp_path / "a.gif"), "--url", served.url, "--token", "wrong", "--quiet"])
    assert rc == 1 and "401" in capsys.readouterr().err
