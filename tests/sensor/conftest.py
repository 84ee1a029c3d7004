"""Shared fixtures for the sensor tests: small real recordings built with the project's own writers
and with dv-processing's."""

from pathlib import Path

import numpy as np
import pytest

from edmcgs.sensor.events import Events
from edmcgs.sensor.files.recording import Recording
from edmcgs.sensor.frames import Frames
from tests.support.recordings import write_dvxplorer


def make_events(n: int, width: int, height: int, *, t0: int = 1_700_000_000_000_000, rate_hz: float = 1e6,
                seed: int = 0) -> Events:
    """n random events at about rate_hz, sorted, starting at t0 (Unix-epoch µs)."""
    rng = np.random.default_rng(seed)
    t = t0 + np.sort(rng.integers(0, max(1, int(n / rate_hz * 1e6)), n)).astype(np.int64)
    return Events(t, rng.integers(0, width, n), rng.integers(0, height, n),
                  rng.choice(np.array([-1, 1], np.int8), n))


def make_recording(n_events=20_000, width=64, height=48, n_anchors=4, channels=3, poses=True, seed=0):
    ev = make_events(n_events, width, height, seed=seed)
    rng = np.random.default_rng(seed + 1)
    t_a = np.linspace(ev.t[0], ev.t[-1], n_anchors).astype(np.int64)
    c2w = np.tile(np.eye(4), (n_anchors, 1, 1))
    c2w[:, :3, 3] = rng.normal(size=(n_anchors, 3))
    anchors = Frames(t_a, rng.integers(0, 256, (n_anchors, height, width, channels), dtype=np.uint8),
                     c2w if poses else None)
    held_images = rng.integers(0, 256, (n_anchors - 1, height, width, channels), dtype=np.uint8)
    held = Frames(t_a[:-1] + 7, held_images, c2w[:-1])
    return Recording(width=width, height=height, events=ev, anchors=anchors, held_out=held,
                     intrinsics=np.array([50.0, 51.0, 32.0, 24.0]), trajectory_t_us=t_a,
                     trajectory_c2w=c2w, contrast_threshold=0.2, sensor="simulated",
                     metadata={"scene": "unit", "seed": seed})


@pytest.fixture(scope="session")
def dvxplorer_path(tmp_path_factory) -> Path:
    """The DVXplorer-like recording, written once per session."""
    return write_dvxplorer(tmp_path_factory.mktemp("dvxplorer") / "person.aedat4")
