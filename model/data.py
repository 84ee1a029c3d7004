"""What training needs from a recording, as plain arrays, plus the event windows it samples.

The model never reads events: the caller injects ``event_map(t0_us, t1_us)``, the signed polarity sum
I_E of the events in [t0_us, t1_us) as float32 [H, W] at the event camera's resolution (the sensor's
accumulation). ``EventGrid`` calls it once per sub-step of a gap between anchors when a step first
needs that gap, and keeps the running sums of the gaps used last (a bounded cache: a recording of
any length), so any window on the grid is one subtraction.
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch

from edmcgs.errors import InvalidInputError, TrainingError
from edmcgs.geometry import Intrinsics, Trajectory, validate_pose

EventMapFn = Callable[[int, int], np.ndarray]
"""(t0_us, t1_us) -> float32 [event_height, event_width] signed polarity sum of events in [t0, t1)."""


@dataclass
class TrainingData:
    """Anchors, held-out frames, the camera and the event source of one recording."""

    anchors_t_us: np.ndarray
    """[F] int64 strictly increasing anchor times."""
    anchor_images: np.ndarray
    """[F, H, W, C] uint8, C = 1 or 3."""
    anchor_poses: np.ndarray
    """[F, 4, 4] float64 c2w of the anchors."""
    intrinsics: Intrinsics
    """The camera of the frames (and of the events, at ``event_size``)."""
    trajectory: Trajectory
    """Event-camera c2w over time."""
    t_end_us: int
    """End of the span to train (>= the last anchor)."""
    event_map: EventMapFn | None = None
    """The injected accumulation; None trains the time-only model."""
    event_size: tuple[int, int] | None = None
    """(width, height) of the event maps; default the image size."""
    held_out_t_us: np.ndarray | None = None
    """[G] int64 times of ground-truth frames for evaluation."""
    held_out_images: np.ndarray | None = None
    """[G, H, W, C] uint8."""
    held_out_poses: np.ndarray | None = None
    """[G, 4, 4] float64 c2w, or None to use the trajectory."""
    contrast_threshold: float | None = None
    """The event camera's contrast threshold C when the recording states it."""
    points_xyz: np.ndarray | None = None
    """[P, 3] float64 3D points of the static scene in the poses' world frame (structure from motion's),
    or None."""
    points_colors: np.ndarray | None = None
    """[P, C] uint8 their colours, C the frames' channels."""

    def __post_init__(self) -> None:
        t = np.asarray(self.anchors_t_us)
        if t.ndim != 1 or t.size == 0 or not np.issubdtype(t.dtype, np.integer):
            raise TrainingError("training needs at least one anchor frame (int64 times)")
        self.anchors_t_us = t.astype(np.int64)
        if np.any(np.diff(self.anchors_t_us) <= 0):
            raise InvalidInputError("anchors_t_us must be strictly increasing")
        f = self.anchors_t_us.size
        img = np.asarray(self.anchor_images)
        if img.dtype != np.uint8 or img.shape[:1] != (f,) or img.ndim != 4 or img.shape[3] not in (1, 3):
            raise InvalidInputError(f"anchor_images must be uint8 [{f}, H, W, 1|3], "
                                    f"got {img.dtype} {img.shape}")
        if (img.shape[2], img.shape[1]) != (self.intrinsics.width, self.intrinsics.height):
            raise InvalidInputError("anchor_images and intrinsics disagree on the image size")
        poses = np.asarray(self.anchor_poses, dtype=np.float64)
        if poses.shape != (f, 4, 4):
            raise InvalidInputError(f"anchor_poses must be [{f}, 4, 4], got {poses.shape}")
        self.anchor_poses = np.stack([validate_pose(p, name=f"anchor_poses[{i}]")
                                      for i, p in enumerate(poses)])
        if int(self.t_end_us) < int(self.anchors_t_us[-1]) or int(self.t_end_us) <= int(self.anchors_t_us[0]):
            raise InvalidInputError("t_end_us must be >= the last anchor and after the first")
        self.t_end_us = int(self.t_end_us)
        if self.event_size is None:
            self.event_size = (self.intrinsics.width, self.intrinsics.height)
        if self.held_out_t_us is not None:
            ht = np.asarray(self.held_out_t_us).astype(np.int64)
            himg = np.asarray(self.held_out_images)
            if himg.dtype != np.uint8 or himg.shape[:1] != ht.shape or himg.shape[1:] != img.shape[1:]:
                raise InvalidInputError("held_out_images must be uint8 [G, H, W, C] like the anchors")
            self.held_out_t_us = ht
        if (self.points_xyz is None) != (self.points_colors is None):
            raise InvalidInputError("points_xyz and points_colors must be given together")
        if self.points_xyz is not None:
            xyz, col = np.asarray(self.points_xyz, dtype=np.float64), np.asarray(self.points_colors)
            if xyz.ndim != 2 or xyz.shape[1] != 3 or not np.isfinite(xyz).all():
                raise InvalidInputError(f"points_xyz must be finite [P, 3], got {xyz.shape}")
            if col.dtype != np.uint8 or col.shape != (len(xyz), img.shape[3]):
                raise InvalidInputError(f"points_colors must be uint8 [{len(xyz)}, {img.shape[3]}] (the "
                                        f"frames' channels), got {col.dtype} {col.shape}")
            self.points_xyz, self.points_colors = xyz, col

    @property
    def channels(self) -> int:
        return int(self.anchor_images.shape[3])

    def held_out_pose(self, i: int) -> np.ndarray:
        """c2w of held-out frame ``i`` (its own pose, else the trajectory at its time)."""
        if self.held_out_poses is not None:
            return np.asarray(self.held_out_poses[i], dtype=np.float64)
        return self.trajectory.at(int(self.held_out_t_us[i]))

    def evaluable(self) -> np.ndarray:
        """Indices of the held-out frames inside [first anchor, t_end] (the model has a state there)."""
        if self.held_out_t_us is None:
            return np.zeros(0, dtype=np.int64)
        t = self.held_out_t_us
        return np.flatnonzero((t >= self.anchors_t_us[0]) & (t <= self.t_end_us))


GRID_CACHE_BYTES = 512 * 2**20
"""Memory the running sums of the gaps used last may take (a 3 s clip's 16 gaps at 346x260 take 98 MB)."""


class EventGrid:
    """Running event sums on ``substeps`` + 1 times per gap (gap n starts at anchor n), made per gap on
    demand and kept for the gaps used last, within ``cache_bytes``.

    times: np.ndarray           # [G, S + 1] int64; times[n, 0] is anchor n, times[n, S] the gap's end
    ends_at_anchor: np.ndarray  # [G] bool, True where times[n, S] is anchor n + 1
    cumulative(n): Tensor       # [S + 1, He, We] float32; [k] = I_E over [times[n, 0], times[n, k])
    nonzero(n): np.ndarray      # [S + 1] bool, True where cumulative(n)[k] has a non-zero pixel (known on
                                # the host, so that training on a GPU never reads a map back to ask)
    """

    def __init__(self, times: np.ndarray, ends_at_anchor: np.ndarray, event_map: EventMapFn,
                 size: tuple[int, int], *, cache_bytes: int = GRID_CACHE_BYTES,
                 device: str | torch.device = "cpu"):
        self.times, self.ends_at_anchor = times, ends_at_anchor
        self.event_map, self.size, self.device = event_map, size, torch.device(device)
        w, h = size
        per_gap = (self.substeps + 1) * h * w * 4
        self.capacity = max(1, int(cache_bytes) // per_gap)
        """Gaps whose running sums are kept."""
        self._cache: OrderedDict[int, torch.Tensor] = OrderedDict()
        self._nonzero: dict[int, np.ndarray] = {}
        self.made = 0
        """Gaps summed so far (a gap summed again after it left the cache counts again)."""

    @classmethod
    def build(cls, data: TrainingData, substeps: int, *, cache_bytes: int = GRID_CACHE_BYTES,
              device: str | torch.device = "cpu") -> EventGrid:
        """The grid of ``data``'s gaps (none summed yet)."""
        if data.event_map is None:
            raise TrainingError("the event branch and event loss need an event source (event_map)")
        anchors = data.anchors_t_us
        starts, ends, at_anchor = [], [], []
        for n, start in enumerate(anchors):
            end = int(anchors[n + 1]) if n + 1 < anchors.size else data.t_end_us
            if end > start:
                starts.append(int(start))
                ends.append(end)
                at_anchor.append(n + 1 < anchors.size)
        k = np.arange(substeps + 1)
        times = np.stack([s + (k * (e - s)) // substeps
                          for s, e in zip(starts, ends, strict=True)]).astype(np.int64)
        return cls(times, np.asarray(at_anchor, dtype=bool), data.event_map, data.event_size,
                   cache_bytes=cache_bytes, device=device)

    @property
    def num_gaps(self) -> int:
        return int(self.times.shape[0])

    @property
    def substeps(self) -> int:
        return int(self.times.shape[1]) - 1

    def cumulative(self, gap: int) -> torch.Tensor:
        """[S + 1, He, We] float32 running sums of gap ``gap`` (the same values whether cached or not)."""
        found = self._cache.get(gap)
        if found is not None:
            self._cache.move_to_end(gap)
            return found
        w, h = self.size
        times = self.times[gap]
        sums = np.zeros((self.substeps + 1, h, w), np.float32)  # summed on the host: nothing read back
        for j in range(self.substeps):
            window = np.asarray(self.event_map(int(times[j]), int(times[j + 1])), dtype=np.float32)
            if window.shape != (h, w):
                raise InvalidInputError(f"event_map returned {window.shape}, expected {(h, w)}")
            np.add(sums[j], window, out=sums[j + 1])
        self._nonzero[gap] = sums.reshape(self.substeps + 1, -1).any(axis=1)
        cum = torch.from_numpy(sums).to(self.device)
        self.made += 1
        self._cache[gap] = cum
        while len(self._cache) > self.capacity:
            self._cache.popitem(last=False)
        return cum

    def nonzero(self, gap: int) -> np.ndarray:
        """[S + 1] bool: which of gap ``gap``'s running sums have a non-zero pixel (kept for every gap
        summed once, a few bytes each)."""
        if gap not in self._nonzero:
            self.cumulative(gap)
        return self._nonzero[gap]
