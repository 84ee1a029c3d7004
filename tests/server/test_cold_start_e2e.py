"""A cold start through a real ``edmcgs-serve --replay REC`` with no checkpoint: the camera's view renders at
once (the newest frame moved by the events), a learner beside the server publishes a model that is
swapped in while a client keeps rendering (no request fails), and Ctrl-C leaves a checkpoint that
``edmcgs train --resume`` continues."""

from __future__ import annotations

import json
import signal
import threading
import time

import httpx

from edmcgs import protocol
from edmcgs.clients.client import Client
from edmcgs.train_cli import main as train_main
from harness.server import ServerProcess, build_scene, metric_values

LEARN = {"EDMCGS_LEARN_PRESET": "demo", "EDMCGS_LEARN_FIRST_STEPS": "5", "EDMCGS_LEARN_ANCHOR_FPS": "10",
         "EDMCGS_LEARN_SET": json.dumps(["init_points=300", "num_control_points=16", "deform_width=16",
                                         "deform_depth=2", "eval_every=0"])}
MODEL_S = 240.0  # the learner's start (torch, numba from the cache) and its first round, on a loaded machine


def test_a_cold_start_serves_at_once_learns_swaps_in_its_model_and_saves_it(tmp_path):
    rec, _ = build_scene(tmp_path / "scene", width=64, height=48, duration_s=2.0, anchor_every_s=0.1,
                         frames_per_anchor=2, event_rate=20_000, init_points=300, control_points=16)
    learnt = tmp_path / "learnt"
    srv = ServerProcess(["--replay", str(rec), "--learn-dir", str(learnt)], env=LEARN)
    statuses: list[int] = []
    versions: list[int | None] = []  # of a live stream's frames, opened before the first model
    stop = threading.Event()

    def watch_live():  # the replay ends long before the model: the swap alone must bring a new frame
        with Client(srv.url) as client, client.stream({"mode": "live", "fps": 10}) as stream:
            while not stop.is_set():
                try:
                    frame = stream.receive(timeout=5)
                except TimeoutError:  # the ended replay's head stands still: no frame meanwhile
                    continue
                if frame is not None:
                    versions.append(frame.model_version)

    def keep_rendering():  # a client rendering the head all along, the swap included
        with httpx.Client(base_url=srv.url, timeout=30) as client:
            while not stop.is_set():
                statuses.append(client.get("/render", params={"format": "msgpack"}).status_code)

    try:
        srv.wait_ready()
        first = httpx.get(srv.url + "/render", timeout=30)
        assert first.status_code == 200, first.text
        assert first.headers[protocol.HEADER_ANCHOR] == "frame"
        assert first.headers[protocol.HEADER_MODEL] == "none"
        posed = httpx.get(srv.url + "/render", params={"pose": ",".join(["0"] * 6 + ["1"])}, timeout=30)
        assert posed.status_code == 503 and "no model has been learnt yet" in posed.json()["detail"]
        renderer = threading.Thread(target=keep_rendering, daemon=True)
        renderer.start()
        watcher = threading.Thread(target=watch_live, daemon=True)
        watcher.start()
        deadline = time.monotonic() + MODEL_S
        while (scene := httpx.get(srv.url + "/scene", timeout=30).json())["learning"]["version"] is None:
            assert time.monotonic() < deadline, f"no model after {MODEL_S} s:\n{srv.log()}"
            assert scene["learning"]["error"] is None, scene["learning"]["error"]
            time.sleep(0.5)
        learning = scene["learning"]
        assert learning["running"] and learning["fed"]["frames"] > 0 and learning["model"]["anchors"] >= 3
        lo, hi = learning["model"]["span_us"]
        assert scene["tau_sources"][0] == {"source": "checkpoint", "t_us_min": lo, "t_us_max": hi,
                                           "t_min": 0.0, "t_max": (hi - lo) / 1e6}
        deadline = time.monotonic() + 60
        while not any(v is not None for v in versions):  # the live stream renders the head again
            assert time.monotonic() < deadline, f"no frame of a learnt model on the live stream: {versions}"
            time.sleep(0.2)
        assert versions[0] is None  # before the model: the frame moved by the events
        time.sleep(1.0)  # the renderer goes on past the swap
        stop.set()
        renderer.join(30)
        watcher.join(30)
        inside = httpx.get(srv.url + "/render", params={"t_us": (lo + hi) // 2}, timeout=30)
        assert inside.status_code == 200 and inside.headers[protocol.HEADER_ANCHOR] == "checkpoint"
        assert int(inside.headers[protocol.HEADER_MODEL]) >= learning["version"]  # (newer ones go on)
        values = metric_values(httpx.get(srv.url + "/metrics", timeout=30).text)
        assert values["edmcgs_learned_model_version"] >= 1 and values["edmcgs_learner_up"] == 1
    finally:
        stop.set()
        code = srv.stop(signal.SIGINT, timeout=120)
    assert statuses and set(statuses) == {200}, sorted(set(statuses))
    assert code == 130, srv.log()
    assert (learnt / "learned.ckpt").is_file() and (learnt / "learned.h5").is_file(), srv.log()
    assert "the learner saved" in srv.log()
    assert train_main([str(learnt / "learned.h5"), "-o", str(learnt / "learned.ckpt"), "--resume",
                       "--steps", "2", "--quiet"]) == 0


def test_a_cold_start_on_an_aedat4_file_with_no_other_argument(tmp_path):
    """``edmcgs-serve --replay REC.aedat4`` with nothing else (the camera's file as dv-processing writes
    it: every frame, no poses, no calibration): the camera's view at once, then a learnt model."""
    from edmcgs.pipeline import all_frames
    from edmcgs.sensor.files.recording import read_recording
    from tests.support.recordings import write_aedat

    h5, _ = build_scene(tmp_path / "scene", width=64, height=48, duration_s=2.0, anchor_every_s=0.1,
                        frames_per_anchor=2, event_rate=20_000, init_points=300, control_points=16)
    rec = read_recording(h5)
    aedat = write_aedat(tmp_path / "street.aedat4", rec.events, all_frames(rec), rec.width, rec.height)
    srv = ServerProcess(["--replay", str(aedat), "--learn-dir", str(tmp_path / "learnt")], env=LEARN)
    try:
        srv.wait_ready()
        first = httpx.get(srv.url + "/render", timeout=30)
        assert first.status_code == 200, first.text
        assert first.headers[protocol.HEADER_ANCHOR] == "frame"
        deadline = time.monotonic() + MODEL_S
        while (learning := httpx.get(srv.url + "/scene", timeout=30).json()["learning"])["version"] is None:
            assert time.monotonic() < deadline, f"no model after {MODEL_S} s:\n{srv.log()}"
            assert learning["error"] is None, learning["error"]
            time.sleep(0.5)
        assert learning["model"]["anchors"] >= 3 and learning["fed"]["frames"] > 0
        lo, hi = learning["model"]["span_us"]
        inside = httpx.get(srv.url + "/render", params={"t_us": (lo + hi) // 2}, timeout=30)
        assert inside.status_code == 200 and inside.headers[protocol.HEADER_ANCHOR] == "checkpoint"
        assert int(inside.headers[protocol.HEADER_MODEL]) >= learning["version"]
    finally:
        srv.stop(signal.SIGINT, timeout=120)
