"""Loaders for public event + RGB dataset layouts, into the same in-memory ``Recording``.

- ``load_dnerf``: the D-NeRF/Blender layout the paper's dataset is released in:
  ``transforms_{train,test}.json`` (``camera_angle_x``; per frame ``file_path``, ``transform_matrix``,
  ``time`` in [0, 1]) and ``events/events.npz`` (x, y int16; t int64 ns; p +-1). Train frames become
  the anchors, test frames the held-out frames.
- ``load_ed3dgs``: E-D3DGS's synthetic layout: one ``transforms.json`` whose ``time`` is in seconds,
  its frames under ``rgb/``, and ``events/*.npz``, one file per frame interval (same columns). The
  dense frames are split into anchors at ``anchor_fps`` and held-out frames.

At the boundary: Blender/OpenGL camera-to-world poses (x right, y up, z backwards) become OpenCV
(x right, y down, z forwards) by flipping the camera's y and z axes; RGBA images are composited over
``background``; event times go from ns to µs (floor); events outside the image are dropped and
counted in ``metadata["event_stats"]``; the principal point is the image centre in our
integer-pixel-centre convention, cx = (W - 1) / 2.
"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path

import numpy as np
from PIL import Image

from edmcgs.errors import EdmcgsError, ReplayFormatError
from edmcgs.geometry import validate_pose
from edmcgs.sensor.events import Events, EventStats
from edmcgs.sensor.files.recording import Recording
from edmcgs.sensor.frames import Frames

BLENDER_TO_OPENCV = np.diag([1.0, -1.0, -1.0, 1.0])
"""Right-multiplied onto a Blender c2w: flips the camera's y and z axes."""


# -------------------------------------------------------------------------------------------- pieces

def _read_json(path: Path) -> dict:
    try:
        data = json.loads(path.read_text())
    except FileNotFoundError as exc:
        raise ReplayFormatError(f"{path} is missing") from exc
    except (OSError, ValueError) as exc:
        raise ReplayFormatError(f"{path} is not readable JSON: {exc}") from exc
    if not isinstance(data, dict) or not isinstance(data.get("frames"), list) or not data["frames"]:
        raise ReplayFormatError(f"{path} must hold a non-empty 'frames' list")
    return data


def _frame_field(path: Path, i: int, frame: dict, key: str):
    if not isinstance(frame, dict) or key not in frame:
        raise ReplayFormatError(f"{path}: frames[{i}] has no {key!r}")
    return frame[key]


def _image_path(root: Path, file_path: str) -> Path:
    """``file_path`` relative to ``root``; D-NeRF often leaves the ".png" off."""
    path = root / file_path
    if path.suffix.lower() not in (".png", ".jpg", ".jpeg") and not path.exists():
        path = path.with_name(path.name + ".png")
    return path


def _load_image(path: Path, background: np.ndarray) -> np.ndarray:
    """uint8 RGB [H, W, 3]; an alpha channel is composited over ``background`` (RGB in [0, 1])."""
    try:
        with Image.open(path) as im:
            im.load()
            if im.mode in ("RGBA", "LA", "PA") or (im.mode == "P" and "transparency" in im.info):
                rgba = np.asarray(im.convert("RGBA"), dtype=np.float64) / 255.0
                rgb = rgba[..., :3] * rgba[..., 3:] + background * (1.0 - rgba[..., 3:])
                return np.round(rgb * 255.0).astype(np.uint8)
            return np.asarray(im.convert("RGB"), dtype=np.uint8)
    except FileNotFoundError as exc:
        raise ReplayFormatError(f"image {path} is missing") from exc
    except OSError as exc:
        raise ReplayFormatError(f"image {path} cannot be read: {exc}") from exc


def _pose(path: Path, i: int, matrix) -> np.ndarray:
    """OpenCV c2w from a Blender ``transform_matrix``."""
    try:
        c2w = validate_pose(matrix, name=f"{path.name} frames[{i}].transform_matrix")
    except EdmcgsError as exc:
        raise ReplayFormatError(str(exc)) from exc
    return c2w @ BLENDER_TO_OPENCV


def _intrinsics(path: Path, data: dict, width: int, height: int) -> np.ndarray:
    """fx, fy, cx, cy from ``camera_angle_x`` (square pixels, centred principal point), or from
    ``fl_x``/``fl_y``/``cx``/``cy`` when given (their cx, cy measured from the image corner)."""
    if "fl_x" in data:
        fx = float(data["fl_x"])
        fy = float(data.get("fl_y", fx))
        cx = float(data.get("cx", width / 2)) - 0.5
        cy = float(data.get("cy", height / 2)) - 0.5
    else:
        angle = data.get("camera_angle_x")
        if not isinstance(angle, int | float) or not 0 < angle < math.pi:
            raise ReplayFormatError(f"{path}: camera_angle_x must be an angle in (0, pi) radians, "
                                    f"got {angle!r}")
        fx = fy = 0.5 * width / math.tan(0.5 * angle)
        cx, cy = (width - 1) / 2, (height - 1) / 2
    k = np.array([fx, fy, cx, cy])
    if not np.isfinite(k).all() or fx <= 0 or fy <= 0:
        raise ReplayFormatError(f"{path}: intrinsics {k.tolist()} are not usable")
    return k


def _read_npz_events(path: Path) -> tuple[np.ndarray, ...]:
    """(t_ns int64, x, y, p) columns of one events file."""
    try:
        with np.load(path) as z:
            missing = {"x", "y", "t", "p"} - set(z.files)
            if missing:
                raise ReplayFormatError(f"{path} lacks event columns {sorted(missing)} (needs x, y, t, p)")
            cols = tuple(np.asarray(z[k]).reshape(-1) for k in ("t", "x", "y", "p"))
    except FileNotFoundError as exc:
        raise ReplayFormatError(f"events file {path} is missing") from exc
    except (OSError, ValueError) as exc:
        raise ReplayFormatError(f"events file {path} cannot be read: {exc}") from exc
    if cols[0].dtype.kind not in "iu":
        raise ReplayFormatError(f"{path}: t must be integer nanoseconds, got dtype {cols[0].dtype}")
    return cols


def _events(files: list[Path], width: int, height: int) -> tuple[Events, EventStats]:
    """All events of ``files`` in time order, t in µs; those outside width x height dropped, counted."""
    cols = [_read_npz_events(f) for f in files]
    t_ns, x, y, p = (np.concatenate([c[i] for c in cols]) for i in range(4))
    order = np.argsort(t_ns, kind="stable")  # files may overlap or come in any order
    t_us = t_ns[order].astype(np.int64) // 1000
    try:
        return Events.from_arrays(t_us, x[order], y[order], p[order], width=width, height=height)
    except EdmcgsError as exc:
        raise ReplayFormatError(f"events in {files[0].parent}: {exc}") from exc


def _poses(path: Path, data: dict) -> np.ndarray:
    """OpenCV c2w [F, 4, 4] of every frame of a transforms file."""
    return np.stack([_pose(path, i, _frame_field(path, i, f, "transform_matrix"))
                     for i, f in enumerate(data["frames"])])


def _frames(root: Path, path: Path, data: dict, times_us: np.ndarray, poses: np.ndarray,
            background: np.ndarray, which: np.ndarray) -> Frames:
    """The frames ``which`` (indices into data["frames"], in time order) with their poses."""
    images = [_load_image(_image_path(root, _frame_field(path, i, data["frames"][i], "file_path")),
                          background) for i in which]
    shapes = {im.shape for im in images}
    if len(shapes) > 1:
        raise ReplayFormatError(f"{path}: images differ in size: {sorted(shapes)}")
    t = times_us[which]
    if len(t) > 1 and np.any(np.diff(t) <= 0):
        raise ReplayFormatError(f"{path}: two frames share the time {t[np.argmax(np.diff(t) <= 0)]} µs")
    return Frames(t, np.stack(images), poses[which])


def _times(path: Path, data: dict) -> np.ndarray:
    times = np.array([_frame_field(path, i, f, "time") for i, f in enumerate(data["frames"])], dtype=object)
    try:
        times = times.astype(np.float64)
    except (TypeError, ValueError) as exc:
        raise ReplayFormatError(f"{path}: every frame's 'time' must be a number") from exc
    if not np.isfinite(times).all():
        raise ReplayFormatError(f"{path}: a frame's 'time' is not finite")
    return times


def _trajectory(t_us: np.ndarray, c2w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Poses in time order, one per time (the first listed wins a shared time)."""
    t, first = np.unique(t_us, return_index=True)
    return t, c2w[first]


# --------------------------------------------------------------------------------------------- D-NeRF

def load_dnerf(root: str | os.PathLike, *, span_us: tuple[int, int] | None = None,
               background=(1.0, 1.0, 1.0)) -> Recording:
    """A D-NeRF/Blender-layout dataset with ``events/events.npz`` (see the module docstring).

    span_us: the event-clock times (µs) of ``time`` 0 and 1; by default the first and last event's.
    background: RGB in [0, 1] under transparent pixels (D-NeRF's white by default).
    """
    root = Path(root)
    bg = np.asarray(background, dtype=np.float64)
    train_path, test_path = root / "transforms_train.json", root / "transforms_test.json"
    train = _read_json(train_path)
    test = _read_json(test_path) if test_path.exists() else None
    first = _load_image(_image_path(root, _frame_field(train_path, 0, train["frames"][0], "file_path")), bg)
    height, width = first.shape[:2]
    events, stats = _events([root / "events" / "events.npz"], width, height)
    if span_us is None:
        if len(events) < 2 or events.t_end <= events.t_start:
            raise ReplayFormatError(f"{root}: the events span no time to map 'time' onto; pass span_us")
        span_us = (events.t_start, events.t_end)
    t0, t1 = (int(v) for v in span_us)
    if t1 <= t0:
        raise ReplayFormatError(f"span_us must be increasing, got {span_us}")

    def split(path: Path, data: dict) -> tuple[Frames, np.ndarray, np.ndarray]:
        times = _times(path, data)
        if times.min() < 0 or times.max() > 1:
            raise ReplayFormatError(f"{path}: 'time' must lie in [0, 1], got [{times.min()}, {times.max()}]")
        t_us = t0 + np.round(times * (t1 - t0)).astype(np.int64)
        poses = _poses(path, data)
        return _frames(root, path, data, t_us, poses, bg, np.argsort(t_us, kind="stable")), t_us, poses

    anchors, t_train, c2w_train = split(train_path, train)
    if test is None:
        held_out, t_test, c2w_test = None, t_train[:0], c2w_train[:0]
    else:
        held_out, t_test, c2w_test = split(test_path, test)
    traj_t, traj_c2w = _trajectory(np.concatenate([t_train, t_test]), np.concatenate([c2w_train, c2w_test]))
    return Recording(
        width=width, height=height, events=events, anchors=anchors, held_out=held_out,
        intrinsics=_intrinsics(train_path, train, width, height), trajectory_t_us=traj_t,
        trajectory_c2w=traj_c2w, sensor="dataset", metadata={
            "source": str(root), "layout": "d-nerf", "span_us": [t0, t1],
            "event_stats": stats.as_dict(), "background": bg.tolist()})


# -------------------------------------------------------------------------------------------- E-D3DGS

def load_ed3dgs(root: str | os.PathLike, *, anchor_fps: float = 5.0, held_out_per_interval: int | None = None,
                background=(1.0, 1.0, 1.0)) -> Recording:
    """E-D3DGS's synthetic layout (see the module docstring).

    anchor_fps: keep every k-th frame as an anchor, k = round(frame rate / anchor_fps) (the frame
    rate is the median over the frame times). held_out_per_interval: the number of the other frames
    kept as held-out ones in each anchor interval, evenly spread (None: all of them).
    """
    root = Path(root)
    bg = np.asarray(background, dtype=np.float64)
    path = root / "transforms.json"
    data = _read_json(path)
    times = _times(path, data)
    order = np.argsort(times, kind="stable")
    t_us = np.round(times * 1e6).astype(np.int64)
    steps = np.diff(times[order])
    if len(order) < 2 or steps.min() <= 0:
        raise ReplayFormatError(f"{path}: needs at least two frames at distinct times")
    if not (math.isfinite(anchor_fps) and anchor_fps > 0):
        raise ReplayFormatError(f"anchor_fps must be positive, got {anchor_fps!r}")
    stride = max(1, round(1.0 / (float(np.median(steps)) * anchor_fps)))
    is_anchor = np.arange(len(order)) % stride == 0
    anchor_idx, rest_idx = order[is_anchor], order[~is_anchor]
    if held_out_per_interval is not None and len(rest_idx):
        per = stride - 1  # other frames between two anchors
        keep_at = np.unique(np.round(np.linspace(0, per - 1, held_out_per_interval)).astype(int)) \
            if held_out_per_interval > 0 else np.empty(0, int)
        pos = (np.arange(len(order)) % stride)[~is_anchor] - 1
        rest_idx = rest_idx[np.isin(pos, keep_at)]

    first = _load_image(_image_path(root, _frame_field(path, 0, data["frames"][0], "file_path")), bg)
    height, width = first.shape[:2]
    files = sorted((root / "events").glob("*.npz"))
    if not files:
        raise ReplayFormatError(f"{root / 'events'} holds no .npz event files")
    events, stats = _events(files, width, height)
    poses = _poses(path, data)
    anchors = _frames(root, path, data, t_us, poses, bg, anchor_idx)
    held_out = _frames(root, path, data, t_us, poses, bg, rest_idx) if len(rest_idx) else None
    traj_t, traj_c2w = _trajectory(t_us, poses)
    return Recording(
        width=width, height=height, events=events, anchors=anchors, held_out=held_out,
        intrinsics=_intrinsics(path, data, width, height), trajectory_t_us=traj_t, trajectory_c2w=traj_c2w,
        sensor="dataset", metadata={
            "source": str(root), "layout": "e-d3dgs", "anchor_stride": stride, "event_files": len(files),
            "event_stats": stats.as_dict(), "background": bg.tolist()})
