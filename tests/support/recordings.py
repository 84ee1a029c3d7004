"""Recordings the tests share, written by the tests themselves with dv-processing's own writer."""

import itertools
from pathlib import Path

import numpy as np

from edmcgs.sensor.events import Events
from edmcgs.sensor.frames import Frames
from edmcgs.sensor.sources.dv_bridge import event_store, image_frame

DATA = Path(__file__).resolve().parent.parent / "data"
"""Real recordings from public packages' test data, each folder with its licence and a README saying where
it came from and how it was cut."""

# A DVXplorer recording as iniVation's DV software writes one: 320x240, Unix-epoch µs, events, IMU and an
# empty trigger stream, no frames.
DVX_SENSOR, DVX_SIZE = "DVXplorer_DXB00010", (320, 240)
DVX_FIRST_US, DVX_LAST_US, DVX_EVENTS, DVX_IMU = 1605537493718345, 1605537494308262, 111_954, 475


def dvxplorer_events(seed: int = 0) -> Events:
    """A person-like blob sweeping the sensor plus background activity: DVX_EVENTS events, 49 % ON,
    spanning exactly [DVX_FIRST_US, DVX_LAST_US]."""
    rng = np.random.default_rng(seed)
    w, h = DVX_SIZE
    t = np.sort(rng.integers(DVX_FIRST_US, DVX_LAST_US + 1, DVX_EVENTS)).astype(np.int64)
    t[0], t[-1] = DVX_FIRST_US, DVX_LAST_US
    phase = (t - DVX_FIRST_US) / (DVX_LAST_US - DVX_FIRST_US)
    cx = 60 + 200 * phase
    on_blob = rng.random(DVX_EVENTS) < 0.9
    x = np.where(on_blob, cx + rng.normal(0, 18, DVX_EVENTS), rng.uniform(0, w, DVX_EVENTS))
    y = np.where(on_blob, 120 + rng.normal(0, 50, DVX_EVENTS), rng.uniform(0, h, DVX_EVENTS))
    x = np.clip(np.rint(x), 0, w - 1).astype(np.int16)
    y = np.clip(np.rint(y), 0, h - 1).astype(np.int16)
    p = np.where(rng.random(DVX_EVENTS) < 0.49, 1, -1).astype(np.int8)
    return Events(t, x, y, p)


def write_dvxplorer(path: Path) -> Path:
    """Write the DVXplorer-like recording with dv-processing's MonoCameraWriter."""
    import dv_processing as dv

    config = dv.io.MonoCameraWriter.Config(DVX_SENSOR)
    config.addEventStream(DVX_SIZE)
    config.addImuStream()
    config.addTriggerStream()
    writer = dv.io.MonoCameraWriter(str(path), config)
    events = dvxplorer_events()
    edges = np.searchsorted(events.t, np.arange(DVX_FIRST_US, DVX_LAST_US + 10_000, 10_000))
    for a, b in itertools.pairwise(edges):  # one packet per 10 ms, as DV writes them
        writer.writeEvents(event_store(events[a:b]))
    rng = np.random.default_rng(1)
    imu_t = np.linspace(DVX_FIRST_US + 443, DVX_LAST_US - 100, DVX_IMU).astype(np.int64)
    for t in imu_t.tolist():
        acc, gyro = rng.normal(0, 0.2, 3), rng.normal(0, 0.5, 3)
        writer.writeImu(dv.IMU(t, 38.15, *acc.tolist(), *gyro.tolist(), 0.0, 0.0, 0.0))
    del writer  # the destructor flushes and closes the file
    return path


def write_aedat(path: Path, events: Events, frames: Frames | None, width: int, height: int,
                camera: str = "DAVIS346_test") -> Path:
    """Write events (and frames) with dv-processing's own MonoCameraWriter."""
    import dv_processing as dv

    if frames is not None:
        config = dv.io.MonoCameraWriter.DAVISConfig(camera, (width, height))
    else:
        config = dv.io.MonoCameraWriter.EventOnlyConfig(camera, (width, height))
    writer = dv.io.MonoCameraWriter(str(path), config)
    writer.writeEvents(event_store(events))
    for i in range(0 if frames is None else len(frames)):
        writer.writeFrame(image_frame(int(frames.t_us[i]), frames.images[i]))
    del writer  # the destructor flushes and closes the file
    return path


def write_tiny_h5(path: Path) -> Path:
    """The tiny sliding-square scene (``tiny_scene``) as an edmcgs HDF5 recording: 200 ms of frames every
    2 ms, events from the ESIM simulator, anchors every 100 ms and two held-out frames between them."""
    from edmcgs.sensor.files.recording import Recording, write_recording
    from edmcgs.synth.esim import simulate_frames
    from tests.support import tiny_scene

    t = tiny_scene.T0 + np.arange(0, 200_001, 2_000, dtype=np.int64)
    frames = np.stack([tiny_scene.image(int(ti)) for ti in t])
    events = simulate_frames(t, frames)
    anchors = t[::50]
    held = t[[25, 75]]
    rec = Recording(
        width=tiny_scene.W, height=tiny_scene.H, events=events,
        anchors=Frames(anchors, np.stack([tiny_scene.to_uint8(tiny_scene.image(int(a))) for a in anchors])),
        held_out=Frames(held, np.stack([tiny_scene.to_uint8(tiny_scene.image(int(h))) for h in held])),
        intrinsics=np.array([40.0, 40.0, (tiny_scene.W - 1) / 2, (tiny_scene.H - 1) / 2]),
        contrast_threshold=0.2, sensor="simulated", metadata={"background": [0.1, 0.1, 0.1]})
    write_recording(path, rec)
    return path


TINY_TRAIN_SETS = ("init_points=500", "num_control_points=24", "deform_width=32", "deform_depth=2",
                   "substeps=4", "max_pair_steps=4", "eval_frames=1", "train_scale=1.0")
"""``edmcgs train --set`` values that make a run on ``write_tiny_h5``'s recording take milliseconds a step."""
