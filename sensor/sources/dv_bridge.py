"""Conversions between dv-processing's types and ours, and its errors into our hierarchy.

dv-processing (OpenCV convention) stores colour frames as BGR; we use RGB everywhere, so colour is
swapped here, in both directions, and nowhere else.
"""

from __future__ import annotations

import re

import dv_processing as dv
import numpy as np

from edmcgs.sensor.events import Events
from edmcgs.sensor.imu import IMU_DTYPE


def dv_error_text(exc: BaseException) -> str:
    """dv-processing's message without its C++ stack trace, on one line."""
    text = str(exc).split("Stacktrace:")[0]
    text = re.sub(r"\S*/dv-processing/\S+\(\d+\):\s*", "", text)  # source-file prefixes
    return " ".join(text.split()) or type(exc).__name__


def store_columns(store) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Raw columns (t int64, x int16, y int16, polarity int8 0/1) of a dv.EventStore."""
    arr = store.numpy()
    return arr["timestamp"], arr["x"], arr["y"], arr["polarity"]


def frame_image(frame) -> np.ndarray:
    """A dv.Frame's image as uint8 [H, W, C]: grey C=1 or RGB C=3 (alpha dropped)."""
    img = np.asarray(frame.image)
    if img.ndim == 2:
        return img[..., None]
    if img.shape[2] == 1:
        return img
    return np.ascontiguousarray(img[..., 2::-1])  # BGR(A) -> RGB


def image_frame(t_us: int, image: np.ndarray):
    """A dv.Frame from our uint8 [H, W, C] image (grey or RGB)."""
    img = image[..., 0] if image.shape[2] == 1 else image[..., ::-1]  # RGB -> BGR
    return dv.Frame(int(t_us), np.ascontiguousarray(img))


def imu_array(samples) -> np.ndarray:
    """IMU_DTYPE [K] from a dv IMU vector."""
    out = np.empty(len(samples), IMU_DTYPE)
    for i, s in enumerate(samples):
        out[i] = (s.timestamp, (s.accelerometerX, s.accelerometerY, s.accelerometerZ),
                  (s.gyroscopeX, s.gyroscopeY, s.gyroscopeZ), s.temperature)
    return out


def event_store(events: Events):
    """A dv.EventStore holding ``events`` (dv's Python API takes events one at a time: ~1.5 M/s)."""
    store = dv.EventStore()
    push = store.push_back
    for t, x, y, p in zip(events.t.tolist(), events.x.tolist(), events.y.tolist(), (events.p > 0).tolist(),
                          strict=True):
        push(t, x, y, p)
    return store


def imu_samples(imu: np.ndarray) -> list:
    """dv.IMU objects from IMU_DTYPE rows (no magnetometer in our samples: written as 0)."""
    return [dv.IMU(int(r["t"]), float(r["temperature"]), *map(float, r["accel"]), *map(float, r["gyro"]),
                   0.0, 0.0, 0.0) for r in imu]
