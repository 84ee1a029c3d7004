"""Shared fixtures for the sensor tests: small real recordings built with the project's own writers."""

from pathlib import Path

import numpy as np
import pytest

from edmcgs.sensor.events import Events
from edmcgs.sensor.files.recording import Recording
from edmcgs.sensor.frames import Frames
from tests.support.recordings import DVXPLORER


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


@pytest.fixture
def dvxplorer_path() -> Path:
    assert DVXPLORER.is_file(), f"the shared test recording is missing: {DVXPLORER}"
    return DVXPLORER


def write_aedat(path: Path, events: Events, frames: Frames | None, width: int, height: int,
                camera: str = "DAVIS346_test") -> Path:
    """Write events (and frames) with dv-processing's own MonoCameraWriter."""
    import dv_processing as dv

    if frames is not None:
        config = dv.io.MonoCameraWriter.DAVISConfig(camera, (width, height))
    else:
        config = dv.io.MonoCameraWriter.EventOnlyConfig(camera, (width, height))
    writer = dv.io.MonoCameraWriter(str(path), config)
    store = dv.EventStore()
    for t, x, y, p in zip(events.t.tolist(), events.x.tolist(), events.y.tolist(), (events.p > 0).tolist(),
                          strict=True):
        store.push_back(t, x, y, p)
    writer.writeEvents(store)
    for i in range(0 if frames is None else len(frames)):
        img = frames.images[i]
        img = img[..., 0] if img.shape[2] == 1 else img[..., ::-1]  # dv frames are BGR
        writer.writeFrame(dv.Frame(int(frames.t_us[i]), np.ascontiguousarray(img)))
    del writer  # the destructor flushes and closes the file
    return path
