"""Served as trained: ``edmcgs-serve --replay REC --checkpoint CKPT`` renders every held-out time of the
checkpoint's own recording as ``edmcgs eval`` does, when the stream carries more frames than the
checkpoint's anchors.

The recording streams a frame every 40 ms (a 25 Hz APS camera); the checkpoint was built on every 5th
(200 ms apart) and its event branch does something, so the window [tau, t) shows in the pixels. A
render must take tau(t) from the checkpoint's anchors, the windows it was trained on, not from the
stream's frames: every held-out frame lies on a stream frame, where the stream's rule would give an
empty window.
"""

from __future__ import annotations

import time

import numpy as np
import pytest
import torch

from edmcgs import protocol
from edmcgs.clients.client import Client
from edmcgs.model.checkpoint import load_checkpoint
from edmcgs.model.eval.evaluation import evaluate
from edmcgs.model.eval.metrics import psnr
from edmcgs.pipeline import split_at, training_data
from edmcgs.sensor.event_map import accumulate
from edmcgs.sensor.files.recording import read_recording
from edmcgs.server.encode import to_uint8
from harness.server import HEIGHT, WIDTH, ServerProcess, build_scene

FRAMES_PER_ANCHOR = 5
SECOND_PASS_TO_MS = 500
"""The replay loops: held-out times up to this (ms from the start) are rendered from its second pass."""


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    """(recording, checkpoint): 1.12 s at 64x48, stream frames every 40 ms, checkpoint anchors every
    200 ms (the last at 1.0 s: three held-out frames lie after it)."""
    folder = tmp_path_factory.mktemp("served_as_trained")
    return build_scene(folder, width=WIDTH, height=HEIGHT, duration_s=1.12, anchor_every_s=0.2,
                       frames_per_anchor=FRAMES_PER_ANCHOR, event_rate=20_000, init_points=2000,
                       control_points=64, event_branch_seed=0)


@pytest.fixture(scope="module")
def offline(scene):
    """What ``edmcgs eval`` computes (``evaluate``, fast rasterizer), with the images it scored."""
    rec_path, ckpt = scene
    model = load_checkpoint(ckpt)
    rec = read_recording(rec_path)
    data = training_data(split_at(rec, model.meta.anchors_us))  # what edmcgs eval scores
    images = []
    render = model.render

    def keep(*args, **kwargs):
        image = render(*args, **kwargs)
        images.append(image.copy())
        return image

    model.render = keep  # evaluate renders each held-out frame once, in order
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # as served (EDMCGS_TORCH_THREADS defaults to 1)
    try:
        rows = evaluate(model, data, fast=True)
    finally:
        torch.set_num_threads(threads)
        del model.render
    assert len(rows) == len(images) == len(data.held_out_t_us) == 29 - 6
    return model, rec, data, rows, images


@pytest.fixture(scope="module")
def server(scene):
    rec, ckpt = scene
    srv = ServerProcess(["--replay", str(rec), "--checkpoint", str(ckpt), "--loop"])
    try:
        srv.wait_ready()
        yield srv
    finally:
        srv.stop()


def wait_for_second_pass(client: Client, to_us: int, timeout: float = 60.0) -> dict:
    """Poll GET /scene until the looping replay's second pass has streamed scene time ``to_us``."""
    deadline = time.monotonic() + timeout
    while True:
        scene = client.scene()
        period = scene["source"]["period_us"]
        if scene["stream_head_us"] is not None and scene["stream_head_us"] >= to_us + period:
            return scene
        assert time.monotonic() < deadline, f"the replay did not reach its second pass: {scene}"
        time.sleep(0.05)


def test_the_event_window_shows_in_the_pixels(offline):
    """The test below can tell the two rules apart: the stream's rule (tau = t on a frame, no events)
    renders another image than the checkpoint's."""
    model, rec, data, rows, images = offline
    row = rows[2]  # 120 ms: 120 ms of events since the checkpoint's anchor at 0
    assert row.t_us - row.anchor_us == 120_000
    stream_rule = model.render(model.deform(row.t_us, None), data.held_out_pose(row.index),
                               model.meta.intrinsics)
    assert np.abs(to_uint8(stream_rule).astype(int) - to_uint8(images[2])).max() > 10
    emap = accumulate(rec.events.time_slice(row.anchor_us, row.t_us), WIDTH, HEIGHT)
    assert np.abs(emap).sum() > 1000


def test_replay_renders_every_held_out_time_as_edmcgs_eval_scores_it(server, scene, offline):
    model, rec, data, rows, images = offline
    first = int(model.meta.anchors_us[0])
    with Client(server.url, timeout=30) as client:
        info = wait_for_second_pass(client, first + SECOND_PASS_TO_MS * 1000)
        assert info["anchors_us"] == model.meta.anchors_us.tolist()
        assert len(rec.anchors) == 29 > len(info["anchors_us"]) == 6  # the stream has more frames
        assert info["source"]["has_frames"] is True and info["source"]["loop"] is True
        assert [set(entry) for entry in info["tau_sources"]] == [set(protocol.TAU_SOURCE_KEYS)]
        assert info["tau_sources"] == [{"source": "checkpoint", "t_us_min": first,
                                        "t_us_max": model.meta.t_end_us, "t_min": 0.0,
                                        "t_max": (model.meta.t_end_us - first) / 1e6}]
        for row, offline_image in zip(rows, images, strict=True):
            pose = data.held_out_pose(row.index)
            pixels, meta = client.render(t_us=row.t_us, pose=pose, format="msgpack")
            assert meta.t_us == row.t_us
            # tau from the checkpoint's anchors, never the stream frame the held-out time lies on
            assert meta.anchor_us == row.anchor_us == model.tau(row.t_us)
            assert meta.anchor_us in model.meta.anchors_us and meta.anchor_us < row.t_us
            assert meta.events == len(rec.events.time_slice(row.anchor_us, row.t_us))
            np.testing.assert_array_equal(pixels, to_uint8(offline_image),
                                          err_msg=f"held-out frame {row.index} at {row.t_us} µs")
            target = data.held_out_images[row.index].astype(np.float32) / 255.0
            # The same pixels, so the same score, up to the uint8 rounding of the wire.
            assert psnr(pixels / 255.0, target) == pytest.approx(row.psnr, abs=2e-3)


def test_ply_download_is_what_export_ply_writes(server, scene, offline, tmp_path):
    """GET /ply at a held-out time: the Gaussians deformed by the same events window as the render, the
    file ``edmcgs export-ply --recording`` writes (and not the one without events)."""
    import httpx
    from plyfile import PlyData

    from edmcgs.cli import main

    rec_path, ckpt = scene
    model, rec, _data, rows, _images = offline
    row = rows[2]  # 120 ms of events since its anchor: the event branch moves the Gaussians
    with Client(server.url, timeout=30) as client:
        wait_for_second_pass(client, row.t_us)
    response = httpx.get(server.url + "/ply", params={"t_us": row.t_us}, timeout=60)
    assert response.status_code == 200, response.text
    assert response.headers["content-type"] == "application/octet-stream"
    assert response.headers["content-disposition"].startswith("attachment; filename=")
    assert int(response.headers[protocol.HEADER_T_US]) == row.t_us
    assert int(response.headers[protocol.HEADER_ANCHOR_US]) == row.anchor_us
    events = len(rec.events.time_slice(row.anchor_us, row.t_us))
    assert int(response.headers[protocol.HEADER_EVENTS]) == events > 1000
    served = tmp_path / "served.ply"
    served.write_bytes(response.content)
    exported, no_events = tmp_path / "exported.ply", tmp_path / "no_events.ply"
    assert main(["export-ply", str(ckpt), "--t-us", str(row.t_us), "--recording", str(rec_path),
                 "-o", str(exported)]) == 0
    assert main(["export-ply", str(ckpt), "--t-us", str(row.t_us), "-o", str(no_events)]) == 0
    tables = [PlyData.read(str(p))["vertex"].data for p in (served, exported, no_events)]
    names = tables[0].dtype.names
    assert names == tables[1].dtype.names and len(tables[0]) == len(tables[1]) == len(model.gaussians)
    for name in names:
        np.testing.assert_allclose(tables[0][name], tables[1][name], rtol=1e-5, atol=1e-6, err_msg=name)
    moved = np.abs(tables[0]["x"] - tables[2]["x"]).max()
    assert moved > 1e-4, "the events window does not move the Gaussians: the comparison proves nothing"


def test_ply_outside_the_span_is_a_416_with_the_valid_range(server, scene, tmp_path):
    import httpx
    from plyfile import PlyData

    from edmcgs.clients.client import TimeUnavailable

    with Client(server.url, timeout=30) as client:
        with pytest.raises(TimeUnavailable) as info:
            client.ply(t=1e6)
        valid = info.value.valid_range
        assert info.value.status == 416 and valid["t_us_min"] <= valid["t_us_max"]
        assert valid["t_max"] < 1e6  # the renderable span, in seconds from the start
        (tmp_path / "head.ply").write_bytes(client.ply())  # no time: the live head
        assert len(PlyData.read(str(tmp_path / "head.ply"))["vertex"].data) > 0
    bad = httpx.get(server.url + "/ply", params={"t": "soon"}, timeout=30)
    assert bad.status_code == 422 and bad.json()["param"] == "t"
