"""A tiny analytic dynamic scene for the model's tests: a bright square sliding over a dark background,
seen by a static camera, with an ideal event camera (round(delta log-luminance / C) per pixel)."""

from __future__ import annotations

import numpy as np

from edmcgs.geometry import Intrinsics, Trajectory
from edmcgs.model.data import TrainingData

T0 = 1_700_000_000_000_000  # Unix-epoch microseconds: float32 cannot hold these
W, H = 48, 32
C = 0.2
INTRINSICS = Intrinsics(40.0, 40.0, (W - 1) / 2, (H - 1) / 2, W, H)


def square_x(t_us: int, x0: float, x1: float, span_us: int) -> float:
    return x0 + (x1 - x0) * (t_us - T0) / span_us


def image(t_us: int, *, x0: float = 8.0, x1: float = 30.0, span_us: int = 200_000, channels: int = 3,
          size: float = 10.0) -> np.ndarray:
    """float [H, W, C] in [0, 1], supersampled 4x so the edge moves smoothly."""
    s = 4
    ys, xs = np.mgrid[0:H * s, 0:W * s]
    u, v = (xs + 0.5) / s - 0.5, (ys + 0.5) / s - 0.5
    left = square_x(t_us, x0, x1, span_us)
    inside = (u >= left) & (u < left + size) & (v >= 11) & (v < 11 + size)
    cover = inside.reshape(H, s, W, s).mean((1, 3))
    bright = np.array([0.9, 0.6, 0.3])[:channels] if channels == 3 else np.array([0.8])
    img = 0.1 + cover[..., None] * (bright - 0.1)
    return img.astype(np.float32)


def to_uint8(img: np.ndarray) -> np.ndarray:
    return np.round(img * 255).astype(np.uint8)


def data(*, anchors_ms=(0, 100, 200), held_ms=(50, 150), channels: int = 3, **motion) -> TrainingData:
    anchors = np.array([T0 + 1000 * a for a in anchors_ms], dtype=np.int64)
    held = np.array([T0 + 1000 * h for h in held_ms], dtype=np.int64)

    def log_lum(t: int) -> np.ndarray:
        img = image(t, channels=channels, **motion)
        lum = img @ np.array([0.299, 0.587, 0.114]) if channels == 3 else img[..., 0]
        return np.log(lum + 1e-3)

    def event_map(t0: int, t1: int) -> np.ndarray:
        return np.round((log_lum(t1) - log_lum(t0)) / C).astype(np.float32)

    poses = np.repeat(np.eye(4)[None], len(anchors), 0)
    return TrainingData(
        anchors_t_us=anchors, anchor_images=np.stack([to_uint8(image(t, channels=channels, **motion))
                                                      for t in anchors]),
        anchor_poses=poses, intrinsics=INTRINSICS, trajectory=Trajectory(anchors, poses),
        t_end_us=int(anchors[-1]), event_map=event_map,
        held_out_t_us=held, held_out_images=np.stack([to_uint8(image(t, channels=channels, **motion))
                                                      for t in held]))
