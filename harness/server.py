"""Real servers for tests and benchmarks: a small synthetic scene (recording + untrained checkpoint),
``edmcgs-serve`` in a subprocess, uvicorn in a thread, and the constants the end-to-end tests share."""

from __future__ import annotations

import math
import os
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

TOKEN = "e2e-secret-token"
WIDTH, HEIGHT = 64, 48
"""The end-to-end tests' scene size and bearer token."""


# --------------------------------------------------------------------------------------- the scene

def build_scene(folder: str | os.PathLike, *, width: int = 346, height: int = 260, duration_s: float = 2.0,
                anchor_every_s: float = 0.25, event_rate: float = 300_000.0, init_points: int | None = None,
                control_points: int | None = None, t0_us: int = 1_600_000_000_000_000, seed: int = 0,
                config_overrides: dict | None = None, frames_per_anchor: int = 1,
                event_branch_seed: int | None = None, train_s: float | None = None) -> tuple[Path, Path]:
    """Write ``scene.h5`` (our recording) and ``scene.ckpt`` (an untrained EdMCGS of it) to ``folder``.

    The model uses the ``demo`` preset (the CPU-sized config the bundled demo is trained with: 6000
    initial Gaussians, 256 control points, a 128x4 deformation MLP), with ``init_points`` Gaussians and
    ``control_points`` control points when given (training densifies the demo to at most 30k Gaussians).

    Anchors are RGB frames of a few coloured discs drifting over a gradient, the camera slides 10 cm
    along x, events are uniform in space and time at ``event_rate`` per second with random polarity;
    times are Unix-like µs from ``t0_us`` (exercising the int64 clock). Returns (recording, checkpoint).

    frames_per_anchor: the recording's frames (its ``anchors`` group, what a replay streams) come
    ``frames_per_anchor`` times as often as the checkpoint's anchors, which are every
    ``frames_per_anchor``-th of them (as ``--anchor-every N`` picks them; the rest are its held-out
    frames). event_branch_seed: give the event branch non-trivial weights (as after training), so that
    renders depend on the events window; None: the untrained branch (no effect). train_s: the
    checkpoint covers only the recording's first ``train_s`` seconds (its anchors, span and trajectory);
    the rest is for online anchors (None: all of it).
    """
    from edmcgs.geometry import Intrinsics, Trajectory
    from edmcgs.model.checkpoint import save_checkpoint
    from edmcgs.model.config import preset
    from edmcgs.model.dynamic import EdMCGS
    from edmcgs.sensor.events import Events
    from edmcgs.sensor.files.recording import Recording, write_recording
    from edmcgs.sensor.frames import Frames

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    span = round(duration_s * 1e6)
    t_end = t0_us + span

    frame_t = t0_us + np.arange(0, span + 1, round(anchor_every_s * 1e6 / frames_per_anchor), dtype=np.int64)
    traj_t = t0_us + np.arange(0, span + 1, 10_000, dtype=np.int64)

    def pose(t_us):
        m = np.eye(4)
        m[0, 3] = 0.1 * (np.asarray(t_us) - t0_us) / span
        return m

    yy, xx = np.mgrid[0:height, 0:width].astype(np.float32)
    images = []
    for t in frame_t:
        s = (t - t0_us) / span
        img = np.stack([xx / width, yy / height, 0.5 + 0.0 * xx], axis=-1) * 0.6
        for k, colour in enumerate(((1, 0.2, 0.2), (0.2, 1, 0.2), (0.2, 0.3, 1))):
            cx = width * (0.25 + 0.25 * k + 0.1 * math.sin(2 * math.pi * (s + k / 3)))
            cy = height * (0.5 + 0.2 * math.cos(2 * math.pi * (s + k / 3)))
            disc = (xx - cx) ** 2 + (yy - cy) ** 2 < (0.12 * height) ** 2
            img[disc] = colour
        images.append((np.clip(img, 0, 1) * 255).astype(np.uint8))
    frame_images = np.stack(images)
    frame_poses = np.stack([pose(t) for t in frame_t])

    n = int(event_rate * duration_s)
    events = Events(np.sort(rng.integers(t0_us, t_end + 1, n)).astype(np.int64),
                    rng.integers(0, width, n).astype(np.uint16), rng.integers(0, height, n).astype(np.uint16),
                    np.where(rng.random(n) < 0.5, 1, -1).astype(np.int8))
    intr = Intrinsics(0.8 * width, 0.8 * width, (width - 1) / 2, (height - 1) / 2, width, height)
    traj_c2w = np.stack([pose(t) for t in traj_t])
    rec = Recording(width=width, height=height, events=events,
                    anchors=Frames(frame_t, frame_images, frame_poses),
                    intrinsics=np.array([intr.fx, intr.fy, intr.cx, intr.cy]),
                    trajectory_t_us=traj_t, trajectory_c2w=traj_c2w, contrast_threshold=0.2,
                    sensor="bench.serve synthetic", metadata={"scene": "bench.serve", "seed": seed})
    rec_path = write_recording(folder / "scene.h5", rec)

    config = preset("demo")
    config = replace(config, init_points=init_points or config.init_points,
                     num_control_points=control_points or config.num_control_points,
                     **(config_overrides or {}))
    n_train, t_train = len(frame_t), t_end
    if train_s is not None:
        t_train = t0_us + round(train_s * 1e6)
        n_train = int(np.searchsorted(frame_t, t_train, side="right"))
        keep = traj_t <= t_train
        traj_t, traj_c2w = traj_t[keep], traj_c2w[keep]
    picked = slice(0, n_train, frames_per_anchor)
    model = EdMCGS.from_arrays(anchors_t_us=frame_t[picked], anchor_images=frame_images[picked],
                               intrinsics=intr, anchor_poses=frame_poses[picked], t_end_us=t_train,
                               trajectory=Trajectory(traj_t, traj_c2w), event_size=(width, height),
                               config=config)
    if event_branch_seed is not None:
        randomize_event_branch(model, event_branch_seed)
    ckpt_path = folder / "scene.ckpt"
    save_checkpoint(model, ckpt_path)
    return Path(rec_path), ckpt_path


def randomize_event_branch(model, seed: int = 0) -> None:
    """Give g_phi and Phi non-trivial weights, as after training."""
    import torch

    gen = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for p in [*model.encoder.parameters(), *model.transition.parameters()]:
            p.copy_(torch.randn(p.shape, generator=gen) * 0.3)
        model.event_scale.fill_(1.0)


# ------------------------------------------------------------------------------- a real server

STARTUP_S = 180.0  # torch import, numba cache load (a recompile after a rasterizer change: ~30 s)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class ServerProcess:
    """``edmcgs-serve`` as a user runs it (``python -m edmcgs.server.cli``), on a free loopback port.

    ``args``: CLI arguments; ``env``: EDMCGS_* settings (the caller's own EDMCGS_* are not inherited).
    Output goes to a log file (``log()``); ``stop()`` sends a signal and waits.
    """

    def __init__(self, args: list[str], env: dict[str, str] | None = None):
        self.port = free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        self.log_path = Path(tempfile.gettempdir()) / f"edmcgs-serve-{self.port}.log"
        self._log = open(self.log_path, "w+b")  # closed in stop()
        full_env = {k: v for k, v in os.environ.items() if not k.startswith("EDMCGS_")} | (env or {})
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "edmcgs.server.cli", *args, "--port", str(self.port)],
            stdout=self._log, stderr=subprocess.STDOUT, env=full_env)

    def log(self) -> str:
        if not self._log.closed:
            self._log.flush()
        return self.log_path.read_text(errors="replace")

    def wait_ready(self, token: str | None = None, timeout: float = STARTUP_S) -> None:
        """Until GET /healthz answers 200; raises with the server's log if it exits or times out."""
        import httpx

        headers = {"Authorization": f"Bearer {token}"} if token else {}
        deadline = time.monotonic() + timeout
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
        raise RuntimeError(f"edmcgs-serve not ready after {timeout} s:\n{self.log()}")

    def wait_streamed(self, seconds: float, token: str | None = None, timeout: float = STARTUP_S) -> None:
        """Until the renderable range reaches ``seconds`` from the scene's start (a replay in real time
        on a loaded machine may take longer than that to stream it)."""
        import httpx

        headers = {"Authorization": f"Bearer {token}"} if token else {}
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            renderable = httpx.get(self.url + "/scene", headers=headers, timeout=5).json()["renderable"]
            if renderable is not None and renderable["t_max"] >= seconds:
                return
            time.sleep(0.1)
        raise RuntimeError(f"edmcgs-serve has not streamed {seconds} s after {timeout} s:\n{self.log()}")

    def rss_mb(self) -> float:
        """Resident memory of the server process (MB)."""
        for line in Path(f"/proc/{self.proc.pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
        raise RuntimeError("no VmRSS")

    def cpu_s(self) -> float:
        """CPU time the server process has used (user + system, all threads), seconds."""
        fields = Path(f"/proc/{self.proc.pid}/stat").read_text().rsplit(")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")

    def stop(self, sig: int = signal.SIGINT, timeout: float = 15.0) -> int:
        """Send ``sig``, wait (kill after ``timeout`` s); returns the exit code."""
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


# ------------------------------------------------------------------------------- measurements


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


def metric_values(text: str) -> dict[str, float]:
    """GET /metrics parsed by prometheus-client's own parser: ``name{label="value",...}`` (labels in
    name order, as the exposition writes them) -> value."""
    from prometheus_client.parser import text_string_to_metric_families

    def escape(value: str) -> str:
        return value.replace("\\", "\\\\").replace("\n", "\\n").replace('"', '\\"')

    out = {}
    for family in text_string_to_metric_families(text):
        for sample in family.samples:
            labels = ",".join(f'{k}="{escape(v)}"' for k, v in sorted(sample.labels.items()))
            out[sample.name + (f"{{{labels}}}" if labels else "")] = sample.value
    return out
