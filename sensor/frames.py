"""A run of timestamped image frames (RGB or APS grey), optionally with camera poses.

Used for the sparse anchor frames of a recording, held-out evaluation frames, and the APS frames a
source delivers alongside its events.
"""

from __future__ import annotations

import numpy as np

from edmcgs.errors import InvalidInputError
from edmcgs.geometry import validate_pose


class Frames:
    """``t_us`` int64 [F] strictly increasing; ``images`` uint8 [F, H, W, C] with C = 1 (grey) or 3 (RGB);
    ``poses`` float64 [F, 4, 4] camera-to-world (OpenCV convention) or None.

    The constructor validates; a grey stack [F, H, W] is accepted and given C = 1.
    """

    __slots__ = ("images", "poses", "t_us")
    __hash__ = None

    def __init__(self, t_us, images, poses=None) -> None:
        t_us = np.asarray(t_us)
        if t_us.size == 0 and t_us.dtype == np.float64:  # an empty list has no dtype
            t_us = t_us.astype(np.int64)
        images = np.asarray(images)
        if t_us.ndim != 1:
            raise InvalidInputError(f"frames t_us must be 1-D, got shape {t_us.shape}")
        if t_us.dtype.kind not in "iu":
            raise InvalidInputError(f"frames t_us must be integer microseconds, got dtype {t_us.dtype}")
        t_us = t_us.astype(np.int64, copy=False)
        if images.ndim == 3:
            images = images[..., None]
        if images.ndim != 4 or images.shape[-1] not in (1, 3):
            raise InvalidInputError(
                f"frames images must be [F, H, W, C] with C in (1, 3), got {images.shape}")
        if images.dtype != np.uint8:
            raise InvalidInputError(f"frames images must be uint8, got dtype {images.dtype}")
        if len(images) != len(t_us):
            raise InvalidInputError(f"frames: {len(t_us)} timestamps but {len(images)} images")
        if len(t_us) > 1 and np.any(np.diff(t_us) <= 0):
            i = int(np.argmax(np.diff(t_us) <= 0))
            raise InvalidInputError(
                f"frames t_us must be strictly increasing, got {t_us[i]} then {t_us[i + 1]} at index {i + 1}")
        if poses is not None:
            poses = np.asarray(poses, dtype=np.float64)
            if poses.shape != (len(t_us), 4, 4):
                raise InvalidInputError(f"frames poses must be [{len(t_us)}, 4, 4], got {poses.shape}")
            for i, pose in enumerate(poses):  # checked only: the stored values stay as given
                validate_pose(pose, name=f"frames pose {i}")
        self._set(t_us, images, poses)

    def _set(self, t_us, images, poses) -> None:
        object.__setattr__(self, "t_us", t_us)
        object.__setattr__(self, "images", images)
        object.__setattr__(self, "poses", poses)

    @classmethod
    def _trusted(cls, t_us: np.ndarray, images: np.ndarray, poses: np.ndarray | None) -> Frames:
        fr = object.__new__(cls)
        fr._set(t_us, images, poses)
        return fr

    @classmethod
    def empty(cls, height: int, width: int, channels: int = 1) -> Frames:
        return cls._trusted(np.empty(0, np.int64), np.empty((0, height, width, channels), np.uint8), None)

    @property
    def height(self) -> int:
        return self.images.shape[1]

    @property
    def width(self) -> int:
        return self.images.shape[2]

    @property
    def channels(self) -> int:
        return self.images.shape[3]

    def __len__(self) -> int:
        return len(self.t_us)

    def __getitem__(self, key: slice) -> Frames:
        if not isinstance(key, slice) or key.step not in (None, 1):
            raise InvalidInputError("frames are sliced with a step-1 slice (to keep time order)")
        poses = None if self.poses is None else self.poses[key]
        return Frames._trusted(self.t_us[key], self.images[key], poses)

    def time_slice(self, t0_us: int, t1_us: int) -> Frames:
        """Frames with t0_us <= t < t1_us (views)."""
        i0, i1 = np.searchsorted(self.t_us, [t0_us, t1_us], side="left")
        return self[int(i0):int(i1)]

    def shifted(self, dt_us: int) -> Frames:
        return Frames._trusted(self.t_us + np.int64(dt_us), self.images, self.poses)

    @classmethod
    def concat(cls, parts: list[Frames]) -> Frames:
        parts = [f for f in parts if len(f)]
        if not parts:
            raise InvalidInputError("Frames.concat needs at least one non-empty part (resolution unknown)")
        if len({(f.height, f.width, f.channels) for f in parts}) > 1:
            raise InvalidInputError("Frames.concat: parts differ in resolution or channels")
        with_poses = {f.poses is not None for f in parts}
        if len(with_poses) > 1:
            raise InvalidInputError("Frames.concat: some parts have poses and some do not")
        poses = np.concatenate([f.poses for f in parts]) if with_poses == {True} else None
        return cls(np.concatenate([f.t_us for f in parts]), np.concatenate([f.images for f in parts]), poses)

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, Frames):
            return NotImplemented
        if (self.poses is None) != (other.poses is None):
            return False
        return (np.array_equal(self.t_us, other.t_us) and np.array_equal(self.images, other.images)
                and (self.poses is None or np.array_equal(self.poses, other.poses)))

    def __repr__(self) -> str:
        span = f", t=[{self.t_us[0]}, {self.t_us[-1]}] µs" if len(self) else ""
        return (f"Frames(n={len(self)}, {self.height}x{self.width}x{self.channels}{span}, "
                f"poses={'yes' if self.poses is not None else 'no'})")
