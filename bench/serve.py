"""Benchmark of the service: a real ``edmcgs-serve`` process, driven over HTTP and the websocket.

    .venv/bin/python -m bench.serve [--json PATH] [--checkpoint CKPT --replay REC] [--seconds S]

Keys (targets of issue 6, on the demo scene at 346x260):
    render_p50_ms            GET /render, one client, the event branch included      <= 25
    render_rps_4_clients     four concurrent clients, each with its own pose          >= 60
    render_p99_ms_4_clients  the same, 99th percentile latency                        <= 150
    stream_fps               one websocket client, live mode asking for 60 fps        >= 30
    event_to_frame_ms        median, an event's arrival in the ring -> a live frame
                             that includes it, received by the client                 <= 50

Without ``--checkpoint``/``--replay`` the bench builds its own scene from the model API (an untrained
EdMCGS initialised from synthetic anchor frames at 346x260 with the default config, and a recording
of random events at ~300k ev/s), because it must run before a trained demo exists; the numbers say
which scene they come from. Client-side latencies include HTTP; all clients run in this process.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

TARGETS = {"render_p50_ms": ("<=", 25.0), "render_rps_4_clients": (">=", 60.0),
           "render_p99_ms_4_clients": ("<=", 150.0), "stream_fps": (">=", 30.0),
           "event_to_frame_ms": ("<=", 50.0)}


# --------------------------------------------------------------------------------------- the scene

def build_scene(folder: str | os.PathLike, *, width: int = 346, height: int = 260, duration_s: float = 2.0,
                anchor_every_s: float = 0.25, event_rate: float = 300_000.0, init_points: int = 20_000,
                control_points: int = 512, t0_us: int = 1_600_000_000_000_000, seed: int = 0,
                config_overrides: dict | None = None) -> tuple[Path, Path]:
    """Write ``scene.h5`` (our recording) and ``scene.ckpt`` (an untrained EdMCGS of it) to ``folder``.

    Anchors are RGB frames of a few coloured discs drifting over a gradient, the camera slides 10 cm
    along x, events are uniform in space and time at ``event_rate`` per second with random polarity;
    times are Unix-like µs from ``t0_us`` (exercising the int64 clock). Returns (recording, checkpoint).
    """
    from edmcgs.model.camera import Intrinsics, Trajectory
    from edmcgs.model.checkpoint import save_checkpoint
    from edmcgs.model.config import EdmcgsConfig
    from edmcgs.model.edmcgs import EdMCGS
    from edmcgs.sensor.events import Events
    from edmcgs.sensor.frames import Frames
    from edmcgs.sensor.recording import Recording, write_recording

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    span = round(duration_s * 1e6)
    t_end = t0_us + span

    anchor_t = t0_us + np.arange(0, span + 1, round(anchor_every_s * 1e6), dtype=np.int64)
    traj_t = t0_us + np.arange(0, span + 1, 10_000, dtype=np.int64)

    def pose(t_us):
        m = np.eye(4)
        m[0, 3] = 0.1 * (np.asarray(t_us) - t0_us) / span
        return m

    yy, xx = np.mgrid[0:height, 0:width].astype(np.float32)
    images = []
    for t in anchor_t:
        s = (t - t0_us) / span
        img = np.stack([xx / width, yy / height, 0.5 + 0.0 * xx], axis=-1) * 0.6
        for k, colour in enumerate(((1, 0.2, 0.2), (0.2, 1, 0.2), (0.2, 0.3, 1))):
            cx = width * (0.25 + 0.25 * k + 0.1 * math.sin(2 * math.pi * (s + k / 3)))
            cy = height * (0.5 + 0.2 * math.cos(2 * math.pi * (s + k / 3)))
            disc = (xx - cx) ** 2 + (yy - cy) ** 2 < (0.12 * height) ** 2
            img[disc] = colour
        images.append((np.clip(img, 0, 1) * 255).astype(np.uint8))
    anchor_images = np.stack(images)
    anchor_poses = np.stack([pose(t) for t in anchor_t])

    n = int(event_rate * duration_s)
    events = Events(np.sort(rng.integers(t0_us, t_end + 1, n)).astype(np.int64),
                    rng.integers(0, width, n).astype(np.uint16), rng.integers(0, height, n).astype(np.uint16),
                    np.where(rng.random(n) < 0.5, 1, -1).astype(np.int8))
    intr = Intrinsics(0.8 * width, 0.8 * width, (width - 1) / 2, (height - 1) / 2, width, height)
    traj_c2w = np.stack([pose(t) for t in traj_t])
    rec = Recording(width=width, height=height, events=events,
                    anchors=Frames(anchor_t, anchor_images, anchor_poses),
                    intrinsics=np.array([intr.fx, intr.fy, intr.cx, intr.cy]),
                    trajectory_t_us=traj_t, trajectory_c2w=traj_c2w, contrast_threshold=0.2,
                    sensor="bench.serve synthetic", metadata={"scene": "bench.serve", "seed": seed})
    rec_path = write_recording(folder / "scene.h5", rec)

    config = EdmcgsConfig(init_points=init_points, num_control_points=control_points,
                          **(config_overrides or {}))
    model = EdMCGS.from_arrays(anchors_t_us=anchor_t, anchor_images=anchor_images, intrinsics=intr,
                               anchor_poses=anchor_poses, t_end_us=t_end,
                               trajectory=Trajectory(traj_t, traj_c2w), event_size=(width, height),
                               config=config)
    ckpt_path = folder / "scene.ckpt"
    save_checkpoint(model, ckpt_path)
    return Path(rec_path), ckpt_path
