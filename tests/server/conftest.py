"""End-to-end fixtures: a tiny scene (recording + untrained checkpoint from the model API) and real
servers — ``edmcgs-serve`` in a subprocess, or uvicorn in a thread when a test must reach inside.
"""

from __future__ import annotations

import time
from pathlib import Path

import httpx
import pytest

from harness.server import HEIGHT, TOKEN, WIDTH, ServerProcess, build_scene


@pytest.fixture(scope="session")
def scene_files(tmp_path_factory) -> tuple[Path, Path]:
    """(recording, checkpoint): 2 s at 64x48, anchors every 0.25 s, 20k events/s, Unix-like µs."""
    folder = tmp_path_factory.mktemp("scene")
    return build_scene(folder, width=WIDTH, height=HEIGHT, event_rate=20_000, init_points=2000,
                       control_points=64)


@pytest.fixture(scope="session")
def server(scene_files):
    """The shared server: the tiny scene replayed in a loop, with a bearer token required."""
    rec, ckpt = scene_files
    srv = ServerProcess(["--replay", str(rec), "--checkpoint", str(ckpt), "--loop"],
                        env={"EDMCGS_TOKEN": TOKEN, "EDMCGS_MAX_WIDTH": "1024", "EDMCGS_MAX_HEIGHT": "1024"})
    try:
        srv.wait_ready(TOKEN)
        # Tests render anywhere in the 2 s scene: let the replay's first pass cover it.
        deadline = time.monotonic() + 30
        while True:
            auth = {"Authorization": f"Bearer {TOKEN}"}
            scene = httpx.get(srv.url + "/scene", headers=auth, timeout=10).json()
            if scene["renderable"] and scene["renderable"]["t_us_max"] >= scene["t_end_us"] - 20_000:
                break
            assert time.monotonic() < deadline, "the replay does not advance"
            time.sleep(0.1)
        yield srv
    finally:
        srv.stop()


@pytest.fixture
def client(server):
    from edmcgs.clients.client import Client

    with Client(server.url, token=TOKEN, timeout=20) as c:
        yield c
