"""End-to-end fixtures: a tiny scene (recording + untrained checkpoint from the model API) and real
servers — ``edmcgs-serve`` in a subprocess, or uvicorn in a thread when a test must reach inside.
"""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import httpx
import pytest

from bench.serve import build_scene

TOKEN = "e2e-secret-token"
WIDTH, HEIGHT = 64, 48
STARTUP_S = 90.0  # torch import + numba cache load; far above the usual ~5 s


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="session")
def scene_files(tmp_path_factory) -> tuple[Path, Path]:
    """(recording, checkpoint): 2 s at 64x48, anchors every 0.25 s, 20k events/s, Unix-like µs."""
    folder = tmp_path_factory.mktemp("scene")
    return build_scene(folder, width=WIDTH, height=HEIGHT, event_rate=20_000, init_points=2000,
                       control_points=64)


class ServerProcess:
    """``edmcgs-serve`` as a user runs it, on a free loopback port."""

    def __init__(self, args: list[str], env: dict[str, str] | None = None):
        self.port = free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        self.log_path = Path(os.environ.get("TMPDIR", "/tmp")) / f"edmcgs-serve-{self.port}.log"
        self._log = open(self.log_path, "w+b")  # closed in stop()
        full_env = {k: v for k, v in os.environ.items() if not k.startswith("EDMCGS_")} | (env or {})
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "edmcgs.server.cli", *args, "--port", str(self.port)],
            stdout=self._log, stderr=subprocess.STDOUT, env=full_env)

    def log(self) -> str:
        if not self._log.closed:
            self._log.flush()
        return self.log_path.read_text(errors="replace")

    def wait_ready(self, token: str | None = None) -> None:
        headers = {"Authorization": f"Bearer {token}"} if token else {}
        deadline = time.monotonic() + STARTUP_S
        while time.monotonic() < deadline:
            if self.proc.poll() is not None:
                raise RuntimeError(f"edmcgs-serve exited with {self.proc.returncode}:\n{self.log()}")
            try:
                if httpx.get(self.url + "/healthz", headers=headers, timeout=2).status_code == 200:
                    return
            except httpx.TransportError:
                pass
            time.sleep(0.2)
        self.stop()
        raise RuntimeError(f"edmcgs-serve not ready after {STARTUP_S} s:\n{self.log()}")

    def rss_mb(self) -> float:
        for line in Path(f"/proc/{self.proc.pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
        raise RuntimeError("no VmRSS")

    def stop(self, sig: int = signal.SIGINT, timeout: float = 15.0) -> int:
        if self.proc.poll() is None:
            self.proc.send_signal(sig)
            try:
                self.proc.wait(timeout)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(5)
        if not self._log.closed:
            self._log.close()
        return self.proc.returncode


@pytest.fixture(scope="session")
def server(scene_files):
    """The shared server: the tiny scene replayed in a loop, with a bearer token required."""
    rec, ckpt = scene_files
    srv = ServerProcess(["--replay", str(rec), "--checkpoint", str(ckpt), "--loop"],
                        env={"EDMCGS_TOKEN": TOKEN, "EDMCGS_MAX_WIDTH": "1024", "EDMCGS_MAX_HEIGHT": "1024"})
    try:
        srv.wait_ready(TOKEN)
        yield srv
    finally:
        srv.stop()


@pytest.fixture
def client(server):
    from edmcgs.clients.client import Client

    with Client(server.url, token=TOKEN, timeout=20) as c:
        yield c


class ThreadServer:
    """uvicorn in a thread of the test process, serving ``create_app(settings, service_factory=...)``."""

    def __init__(self, app):
        import uvicorn

        self.port = free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        config = uvicorn.Config(app, host="127.0.0.1", port=self.port, log_level="warning",
                                timeout_graceful_shutdown=2)
        self.server = uvicorn.Server(config)
        self.thread = threading.Thread(target=self.server.run, name="uvicorn-test", daemon=True)

    def __enter__(self) -> ThreadServer:
        self.thread.start()
        deadline = time.monotonic() + STARTUP_S
        while not self.server.started:
            if not self.thread.is_alive() or time.monotonic() > deadline:
                raise RuntimeError("the in-thread server did not start")
            time.sleep(0.05)
        return self

    def __exit__(self, *exc) -> None:
        self.server.should_exit = True
        self.thread.join(15)
        assert not self.thread.is_alive(), "uvicorn did not stop"
