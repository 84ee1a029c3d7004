"""A cold-start scene on a local Ray Serve (``ray.init(num_cpus=2)``): no checkpoint, a recording played as
a camera; the scene's one learner (``ray_serve/learner.py``) trains on the shared stream, both render
replicas answer at once and then serve the same learnt models, and the learner saves what it learnt when
the scene stops."""

from __future__ import annotations

import time

import httpx
import pytest

pytest.importorskip("ray.serve", reason="the 'ray' extra is not installed")

from harness.ray_serve import LocalServe
from harness.server import build_scene

pytestmark = pytest.mark.slow

REPLICA, MODEL = "x-edmcgs-replica", "x-edmcgs-model"
MODEL_S = 240.0  # Ray's start, the learner's (torch, numba from the cache) and its first round, loaded


def test_a_cold_start_scene_learns_once_and_every_replica_serves_its_models(tmp_path):
    rec, _ = build_scene(tmp_path / "scene", width=64, height=48, duration_s=2.0, anchor_every_s=0.1,
                         frames_per_anchor=2, event_rate=20_000, init_points=300, control_points=16)
    learnt = tmp_path / "learnt"
    scene = {"name": "learn", "replay": str(rec), "live": True, "replicas": 2, "cpus_per_replica": 0.25,
             "settings": {"raster_threads": 1, "learn_dir": str(learnt), "learn_preset": "demo",
                          "learn_first_steps": 5, "learn_anchor_fps": 10, "online_fit_steps": 0,
                          "learn_set": ["init_points=300", "num_control_points=16", "deform_width=16",
                                        "deform_depth=2", "eval_every=0"]}}
    with LocalServe([scene]) as local:
        listed = httpx.get(local.url + "/scenes", timeout=30).json()["scenes"][0]
        assert listed["checkpoint"] == "learnt while serving (cold start)"
        assert local.running_replicas("learner-learn") == 1 and local.running_replicas("scene-learn") == 2
        before: set[str] = set()  # replicas that rendered the camera's view with no model yet
        served: dict[str, str] = {}  # replica -> the learnt model version it rendered with last
        deadline = time.monotonic() + MODEL_S
        while len(served) < 2 or len(set(served.values())) > 1:
            assert time.monotonic() < deadline, f"no model on both replicas: {served}, none yet on {before}"
            r = httpx.get(local.url + "/scenes/learn/render", params={"format": "jpeg"}, timeout=30)
            if r.status_code != 200:  # before the first frame reached that replica
                assert r.status_code == 503, r.text
                continue
            if r.headers[MODEL] == "none":
                before.add(r.headers[REPLICA])
            else:
                served[r.headers[REPLICA]] = r.headers[MODEL]
        assert before, "a replica rendered before any model was learnt"
        learning = httpx.get(local.url + "/scenes/learn/scene", timeout=30).json()["learning"]
        assert learning["model"]["version"] >= 1 and learning["error"] is None
        assert learning["workdir"] == str(learnt) and learning["fed"]["frames"] > 0
    assert (learnt / "learned.ckpt").is_file() and (learnt / "learned.h5").is_file()
