"""From a recording to what the model trains on: the application layer's one adapter.

Every command (``edmcgs train``, ``edmcgs eval``, ``edmcgs record``), the server and the benchmarks
turn a recording into the model's plain arrays and config here; the model never sees the sensor's
types, the sensor never the model's.

Any recording the sensor layer reads comes in (``open_recording``: our HDF5 as stored; every other
format, ``edmcgs.sensor.sources.open.FORMATS``, replayed into memory, with the calibration and
ground-truth trajectory it states), with what the file cannot say given by the user: which frames are
anchors (``--anchor-fps`` / ``--anchor-every``: the other frames become held-out ground truth), the
camera (``--intrinsics fx,fy,cx,cy`` or a DV calibration file) and its poses (``--poses`` TUM file, or
``--poses auto``: structure from motion over all its frames, ``edmcgs.poses``).
"""

from __future__ import annotations

import math
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

from edmcgs.atomic import atomic_output
from edmcgs.errors import InvalidInputError, PoseError, TrainingError
from edmcgs.geometry import Intrinsics, Similarity, Trajectory, pose_from_quat, rotmat_to_quat, validate_pose
from edmcgs.model.config import EdmcgsConfig, preset
from edmcgs.model.data import TrainingData
from edmcgs.model.dynamic import EdMCGS
from edmcgs.model.motion.leanness import events_decision
from edmcgs.options import AUTO_POSES, RecordingOptions
from edmcgs.sensor.event_map import accumulate
from edmcgs.sensor.files.event_file import FileEvents
from edmcgs.sensor.files.recording import FORMAT_NAME, Recording, read_recording
from edmcgs.sensor.frames import Frames
from edmcgs.sensor.record import read_source
from edmcgs.sensor.sources.open import detect_format, open_source, parse_resolution
from edmcgs.sensor.sources.pacing import Pacing

_FOREVER = 2**62  # a time bound past any real timestamp


def recording_intrinsics(rec: Recording) -> Intrinsics:
    """The recording's pinhole camera; without one, a centred camera with a 53-degree horizontal view."""
    if rec.intrinsics is not None:
        fx, fy, cx, cy = (float(v) for v in rec.intrinsics)
        return Intrinsics(fx, fy, cx, cy, rec.width, rec.height)
    print("warning: the recording has no intrinsics; assuming fx = fy = width, centred principal point",
          file=sys.stderr)
    return Intrinsics(float(rec.width), float(rec.width), (rec.width - 1) / 2, (rec.height - 1) / 2,
                      rec.width, rec.height)


def training_data(rec: Recording) -> TrainingData:
    """Turn a recording into the model's arrays; poses default to the trajectory, then to a static camera."""
    anchors = rec.anchors
    if len(anchors) == 0:
        raise TrainingError("the recording has no anchor frames: EdMCGS needs at least one RGB/APS frame")
    if (anchors.width, anchors.height) != (rec.width, rec.height):
        raise TrainingError("anchor frames and events differ in resolution; resample the frames first")
    if rec.trajectory_t_us is not None:
        trajectory = Trajectory(rec.trajectory_t_us, rec.trajectory_c2w)
    elif anchors.poses is not None:
        trajectory = Trajectory(anchors.t_us, anchors.poses)
    else:
        trajectory = Trajectory(anchors.t_us[:1], np.eye(4)[None])
    poses = anchors.poses if anchors.poses is not None else trajectory.at(anchors.t_us)
    ends = [int(anchors.t_us[-1])]
    if len(rec.events):
        ends.append(int(rec.events.t_end) + 1)
    held = rec.held_out
    if held is not None and len(held):
        ends.append(int(held.t_us[-1]))
    width, height, events = rec.width, rec.height, rec.events

    def event_map(t0_us: int, t1_us: int) -> np.ndarray:
        if isinstance(events, FileEvents):  # left in the file: read a block at a time
            return accumulate(events.read(t0_us, t1_us), width, height)
        return accumulate(events.time_slice(t0_us, t1_us), width, height)

    return TrainingData(
        anchors_t_us=anchors.t_us, anchor_images=anchors.images, anchor_poses=poses,
        intrinsics=recording_intrinsics(rec), trajectory=trajectory, t_end_us=max(ends),
        event_map=event_map if len(events) else None, event_size=(width, height),
        held_out_t_us=None if held is None or not len(held) else held.t_us,
        held_out_images=None if held is None or not len(held) else held.images,
        held_out_poses=None if held is None or not len(held) else held.poses,
        contrast_threshold=rec.contrast_threshold, points_xyz=rec.points_xyz, points_colors=rec.points_colors)


def new_model(data: TrainingData, cfg: EdmcgsConfig) -> EdMCGS:
    """An untrained EdMCGS for ``data`` with ``cfg``, initialised from its anchor frames."""
    return EdMCGS.from_arrays(anchors_t_us=data.anchors_t_us, anchor_images=data.anchor_images,
                              intrinsics=data.intrinsics, anchor_poses=data.anchor_poses,
                              t_end_us=data.t_end_us, trajectory=data.trajectory, event_size=data.event_size,
                              config=cfg, points_xyz=data.points_xyz, points_colors=data.points_colors)


def default_preset(rec: Recording) -> tuple[str, str]:
    """(preset, why) for a recording trained with no ``--config``: ``moving`` for a camera that
    translates, with the 3D points structure from motion gave with its poses (``--poses auto``: the
    static set starts on them); else ``demo``."""
    poses = rec.metadata.get("poses", {})
    if rec.points_xyz is not None and len(rec.points_xyz) and not poses.get("static") \
            and not poses.get("rotation_only"):
        return "moving", (f"a moving camera, with its poses and {len(rec.points_xyz)} points from structure "
                          "from motion")
    return "demo", "the CPU-sized preset"


def build_config(name: str, overrides: list[str], rec: Recording) -> EdmcgsConfig:
    """Preset, then what the recording states (contrast threshold, a synthetic scene's constant
    background colour), then ``--set`` overrides, then what the data leaves out (no events: no event
    branch, said on stdout)."""
    cfg = preset(name)
    if rec.contrast_threshold is not None:
        cfg = cfg.replace(contrast_threshold=float(rec.contrast_threshold))
    background = rec.metadata.get("background")
    if isinstance(background, list) and len(background) == 3:
        cfg = cfg.replace(background=tuple(float(v) for v in background))
    cfg = cfg.with_overrides(overrides)
    events, message = events_decision(len(rec.events), cfg.events)
    if message is not None:
        print(f"edmcgs train: {message}")
        cfg = cfg.replace(events=events)
    return cfg


# ------------------------------------------------------------------ any recording in


def open_recording(path: str | Path, options: RecordingOptions | None = None, *, progress: bool = False,
                   start_s: float = 0.0, duration_s: float | None = None, frames: bool = True,
                   lazy_events: bool = False) -> Recording:
    """The recording at ``path`` in any format the sensor layer reads, with ``options`` applied; cut to
    ``start_s`` .. ``duration_s`` as ``edmcgs record`` cuts a copy (``cut``), and without its frames when
    ``frames`` is False. lazy_events: our HDF5's events stay in the file, read a window at a time
    (``FileEvents``: training a recording of any length); every other format is replayed into memory
    (``edmcgs record`` it to HDF5 first)."""
    path = Path(path)
    options = RecordingOptions() if options is None else options
    if detect_format(path) == "hdf5" and _is_ours(path):
        rec = read_recording(path, lazy_events=lazy_events)
    else:
        resolution = parse_resolution(options.resolution)
        with open_source(path, pacing=Pacing(factor=0), resolution=resolution) as src:
            rec = read_source(src, progress=progress, source_name=path.name)
        dropped = rec.metadata.get("source_stats", {}).get("dropped", 0)
        if dropped:
            print(f"note: {dropped} invalid events of {path.name} were dropped: "
                  f"{rec.metadata['source_stats']}", file=sys.stderr)
        if rec.metadata.get("lens_distortion") and options.intrinsics is None:
            print(f"warning: {path.name} states a lens distortion {rec.metadata['lens_distortion']}, which "
                  "the pinhole model does not undo; undistort the recording first for the best fit",
                  file=sys.stderr)
    if start_s or duration_s is not None:
        rec = cut(rec, start_s=start_s, duration_s=duration_s)
    if not frames:
        if options.anchor_fps is not None or options.anchor_every is not None:
            raise InvalidInputError("without frames there are no anchors to choose: leave out --no-frames or "
                                    "--anchor-fps / --anchor-every")
        rec = replace(rec, anchors=Frames.empty(rec.height, rec.width), held_out=None)
    if options.intrinsics is not None:
        rec = replace(rec, intrinsics=parse_intrinsics(options.intrinsics, rec.width, rec.height))
    if options.poses == AUTO_POSES:
        rec = estimated_poses(rec, progress=progress)
    elif options.poses is not None:
        t_us, c2w = read_tum(options.poses)
        span = rec.t_range_us
        if span is not None and (t_us[-1] < span[0] or t_us[0] > span[1]):
            raise InvalidInputError(f"{options.poses}: its times {t_us[0]}..{t_us[-1]} µs miss the "
                                    f"recording's {span[0]}..{span[1]} µs (TUM times are seconds on the "
                                    "recording's clock)")
        rec = with_trajectory(rec, t_us, c2w)
    if options.anchor_fps is not None or options.anchor_every is not None:
        rec = split_frames(rec, fps=options.anchor_fps, every=options.anchor_every)
    return rec


def cut(rec: Recording, *, start_s: float = 0.0, duration_s: float | None = None) -> Recording:
    """``rec`` from ``start_s`` after its first timestamp, for ``duration_s`` counted from the first event
    from there (as ``edmcgs record`` copies a replay); events and frames outside dropped, the trajectory
    kept whole (poses are interpolated from it)."""
    if not (math.isfinite(start_s) and start_s >= 0):
        raise InvalidInputError(f"--start must be >= 0 seconds, got {start_s}")
    if duration_s is not None and not (math.isfinite(duration_s) and duration_s > 0):
        raise InvalidInputError(f"--duration must be a positive number of seconds, got {duration_s}")
    span = rec.t_range_us
    if span is None:
        return rec
    begin = span[0] + round(start_s * 1e6)
    if begin > span[1]:
        raise InvalidInputError(f"--start {start_s:g} s is past the end of the recording "
                                f"({(span[1] - span[0]) / 1e6:g} s long)")
    events = rec.events.time_slice(begin, _FOREVER)
    first = begin if events.t_start is None else events.t_start
    stop = _FOREVER if duration_s is None else first + round(duration_s * 1e6)

    def window(frames: Frames | None) -> Frames | None:
        return None if frames is None else frames.time_slice(begin, stop)

    held = window(rec.held_out)
    return replace(rec, events=events.time_slice(begin, stop), anchors=window(rec.anchors),
                   held_out=held if held is not None and len(held) else None)


def with_trajectory(rec: Recording, t_us: np.ndarray, c2w: np.ndarray) -> Recording:
    """``rec`` whose camera follows the trajectory (t_us, c2w): the frames' own poses are dropped, and so
    are 3D points the recording had (they belong to its former world frame)."""
    anchors = Frames(rec.anchors.t_us, rec.anchors.images)
    held = None if rec.held_out is None else Frames(rec.held_out.t_us, rec.held_out.images)
    return replace(rec, anchors=anchors, held_out=held, trajectory_t_us=np.asarray(t_us, dtype=np.int64),
                   trajectory_c2w=np.asarray(c2w, dtype=np.float64), points_xyz=None, points_colors=None)


def estimated_poses(rec: Recording, *, progress: bool = False, threads: int = -1) -> Recording:
    """``rec`` with the poses structure from motion finds over all its frames (anchors and held-out
    alike), its 3D points (in the poses' frame), the camera it estimated when the recording had none,
    and how in ``metadata["poses"]``; a camera that did not move becomes a static one (one pose), said
    here. Novel views (a second camera's frames, their poses in the recording's former world frame) are
    carried into the new frame by the similarity that aligns the former poses of the registered frames
    with the estimated ones, and dropped, said here, when the recording had no former poses."""
    from edmcgs.poses import estimate_poses

    frames = all_frames(rec)
    given = None if rec.intrinsics is None else Intrinsics(*(float(v) for v in rec.intrinsics), rec.width,
                                                           rec.height)
    estimate = estimate_poses(frames.t_us, frames.images, given, imu=rec.imu, progress=progress,
                              threads=threads)
    print(f"poses from the frames: {estimate.summary()}")
    if estimate.intrinsics is not None and given is None:
        k = estimate.intrinsics
        rec = replace(rec, intrinsics=np.array([k.fx, k.fy, k.cx, k.cy]))
    metadata = {**rec.metadata, "poses": {
        "source": "structure from motion", "frames": estimate.frames, "registered": estimate.registered,
        "static": estimate.static, "rotation_only": estimate.rotation_only,
        "estimated_intrinsics": estimate.estimated_intrinsics,
        "distortion": estimate.distortion, "seconds": round(estimate.seconds, 3), "imu": estimate.imu}}
    former = _former_poses(rec, frames, estimate.t_us)
    out = replace(with_trajectory(rec, estimate.t_us, estimate.c2w), metadata=metadata,
                  points_xyz=estimate.point_xyz, points_colors=estimate.point_colors)
    if rec.novel_views is not None and len(rec.novel_views):
        out = replace(out, novel_views=_novel_views_moved(rec.novel_views, former, estimate))
    return out


def _former_poses(rec: Recording, frames: Frames, t_us: np.ndarray) -> np.ndarray | None:
    """The recording's own c2w at ``t_us`` (frame times) before structure from motion replaced them:
    the frames' poses, else its trajectory's; None when it had neither."""
    if frames.poses is not None:
        return frames.poses[np.searchsorted(frames.t_us, t_us)]
    if rec.trajectory_t_us is not None:
        return Trajectory(rec.trajectory_t_us, rec.trajectory_c2w).at(t_us)
    return None


def _novel_views_moved(views: Frames, former: np.ndarray | None, estimate) -> Frames | None:
    if former is None or estimate.static or estimate.rotation_only:
        print(f"note: the recording's {len(views)} novel views are left out: their poses are in a world "
              "frame the estimated poses cannot be related to", file=sys.stderr)
        return None
    try:
        to_estimated = Similarity.fit_poses(former, estimate.c2w)
    except InvalidInputError:
        print(f"note: the recording's {len(views)} novel views are left out: its former camera did not "
              "move, so their poses cannot be related to the estimated ones", file=sys.stderr)
        return None
    return Frames(views.t_us, views.images, to_estimated.poses(views.poses))


def _is_ours(path: Path) -> bool:
    import h5py

    try:
        with h5py.File(path, "r") as f:
            return f.attrs.get("format") == FORMAT_NAME
    except OSError:
        return True  # not HDF5 at all: read_recording says so, naming the file


def all_frames(rec: Recording) -> Frames:
    """Anchors and held-out frames together, in time order."""
    parts = [f for f in (rec.anchors, rec.held_out) if f is not None and len(f)]
    if len(parts) < 2:
        return parts[0] if parts else rec.anchors
    t = np.concatenate([f.t_us for f in parts])
    order = np.argsort(t, kind="stable")
    poses = None  # poses for some frames only: the trajectory decides
    if all(f.poses is not None for f in parts):
        poses = np.concatenate([f.poses for f in parts])[order]
    if np.any(np.diff(t[order]) <= 0):
        raise InvalidInputError("two frames of the recording share a timestamp")
    return Frames(t[order], np.concatenate([f.images for f in parts])[order], poses)


def split_frames(rec: Recording, *, fps: float | None = None, every: int | None = None) -> Recording:
    """Every frame of ``rec`` (anchors and held-out alike) re-split: anchors every ``every``-th frame, or
    the frame nearest each tick of a ``fps`` clock started at the first frame; the rest held out."""
    frames = all_frames(rec)
    n = len(frames)
    if n == 0:
        raise InvalidInputError("the recording has no frames to choose anchors among")
    if (fps is None) == (every is None):
        raise InvalidInputError("give one of --anchor-fps and --anchor-every")
    if every is not None:
        if isinstance(every, bool) or every < 1:
            raise InvalidInputError(f"--anchor-every must be a positive integer, got {every}")
        picked = np.arange(0, n, every)
    else:
        if not (math.isfinite(fps) and fps > 0):
            raise InvalidInputError(f"--anchor-fps must be a positive number, got {fps}")
        t = frames.t_us
        ticks = np.arange(t[0], t[-1] + 1, 1e6 / fps)
        right = np.clip(np.searchsorted(t, ticks), 0, n - 1)
        left = np.clip(right - 1, 0, n - 1)
        picked = np.unique(np.where(np.abs(t[left] - ticks) <= np.abs(t[right] - ticks), left, right))
    return split_at(rec, frames.t_us[picked], frames=frames)


def split_at(rec: Recording, anchors_us: np.ndarray, *, frames: Frames | None = None) -> Recording:
    """``rec`` with the frames at ``anchors_us`` as anchors and every other frame held out (a checkpoint's
    anchor times give back the split it was trained with)."""
    frames = all_frames(rec) if frames is None else frames
    anchors_us = np.asarray(anchors_us, dtype=np.int64)
    is_anchor = np.isin(frames.t_us, anchors_us)
    if int(is_anchor.sum()) != len(anchors_us):
        missing = np.setdiff1d(anchors_us, frames.t_us)
        raise InvalidInputError(f"the recording has no frames at {len(missing)} of the anchor times "
                                f"(first: {missing[:3].tolist()} µs): it is not the recording they came from")

    def pick(mask):
        return Frames(frames.t_us[mask], frames.images[mask],
                      None if frames.poses is None else frames.poses[mask])

    held = pick(~is_anchor)
    return replace(rec, anchors=pick(is_anchor), held_out=held if len(held) else None)


def write_tum(path: str | Path, t_us: np.ndarray, c2w: np.ndarray) -> None:
    """Write a TUM trajectory (what ``read_tum`` reads: t in seconds, OpenCV camera-to-world, the
    quaternion x y z w), atomically."""
    q = rotmat_to_quat(np.asarray(c2w)[:, :3, :3]) + 0.0  # w x y z
    lines = ["# t tx ty tz qx qy qz qw (seconds; OpenCV camera-to-world: x right, y down, z forward)"]
    for t, pose, (w, x, y, z) in zip(np.asarray(t_us, dtype=np.int64), c2w, q, strict=True):
        tx, ty, tz = pose[:3, 3] + 0.0  # + 0.0: no "-0.000000000"
        sign, t = ("-" if t < 0 else ""), abs(int(t))  # exact to the microsecond, whatever the epoch
        lines.append(f"{sign}{t // 1_000_000}.{t % 1_000_000:06d} {tx:.9f} {ty:.9f} {tz:.9f} "
                     f"{x:.9f} {y:.9f} {z:.9f} {w:.9f}")
    with atomic_output(Path(path)) as tmp:
        Path(tmp).write_text("\n".join(lines) + "\n")


def read_tum(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """A TUM trajectory (``t tx ty tz qx qy qz qw`` per line, ``#`` comments, t in seconds) as
    (int64 [T] µs, float64 [T, 4, 4] camera-to-world, OpenCV axes)."""
    path = Path(path)
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as exc:
        raise InvalidInputError(f"{path}: cannot read the trajectory: {exc}") from exc
    rows = []
    for number, line in enumerate(text.splitlines(), 1):
        line = line.split("#")[0].strip()
        if not line:
            continue
        try:
            values = [float(v) for v in line.replace(",", " ").split()]
        except ValueError:
            values = []
        if len(values) != 8 or not all(math.isfinite(v) for v in values):
            raise InvalidInputError(f"{path}:{number}: expected 8 numbers 't tx ty tz qx qy qz qw' (TUM: "
                                    f"the quaternion's w last), got {line!r}")
        rows.append(values)
    if not rows:
        raise InvalidInputError(f"{path}: no poses in the trajectory file")
    data = np.array(rows)
    t_us = np.rint(data[:, 0] * 1e6).astype(np.int64)
    if np.any(np.diff(t_us) <= 0):
        raise InvalidInputError(f"{path}: times must be strictly increasing (to the microsecond)")
    try:
        c2w = np.stack([validate_pose(pose_from_quat(r[1:4], [r[7], r[4], r[5], r[6]]),  # TUM: x y z w
                                      name=f"{path} pose {i}") for i, r in enumerate(data)])
    except PoseError as exc:
        raise InvalidInputError(str(exc)) from exc
    return t_us, c2w


def parse_intrinsics(text: str, width: int, height: int) -> np.ndarray:
    """fx, fy, cx, cy from ``fx,fy,cx,cy`` or a DV calibration file (refusing a lens it cannot model)."""
    if Path(text).suffix.lower() not in (".json", ".xml"):
        try:
            k = np.array([float(v) for v in text.split(",")])
        except ValueError:
            k = np.zeros(0)
        if k.shape != (4,) or not np.isfinite(k).all() or k[0] <= 0 or k[1] <= 0:
            raise InvalidInputError(f"--intrinsics must be fx,fy,cx,cy (pixels, fx and fy > 0) or a DV "
                                    f"calibration file (.json, .xml), got {text!r}")
        return k
    import dv_processing as dv

    try:
        calibrations = dv.camera.CalibrationSet.LoadFromFile(text)
        cameras = calibrations.getCameraList()
        camera = calibrations.getCameraCalibration(cameras[0]) if cameras else None
    except (RuntimeError, ValueError, IndexError) as exc:
        raise InvalidInputError(f"{text}: not a readable DV camera calibration: {exc}") from exc
    if camera is None:
        raise InvalidInputError(f"{text}: the calibration file holds no camera")
    if tuple(camera.resolution) != (width, height):
        raise InvalidInputError(f"{text}: calibrated at {tuple(camera.resolution)}, the recording is "
                                f"{(width, height)}")
    shift = _distortion_px(camera, width, height)
    if shift > 0.5:
        raise InvalidInputError(f"{text}: its lens distortion ({camera.distortionModel}) moves pixels by up "
                                f"to {shift:.1f} px, which a pinhole model does not undo; undistort the "
                                "recording first, or give --intrinsics fx,fy,cx,cy to accept the error")
    (fx, fy), (cx, cy) = camera.focalLength, camera.principalPoint
    return np.array([fx, fy, cx, cy], dtype=np.float64)


def _distortion_px(camera, width: int, height: int) -> float:
    """Largest displacement (px) the calibration's lens distortion gives a point of the image border."""
    (fx, fy), (cx, cy) = camera.focalLength, camera.principalPoint
    d = np.zeros(5)
    d[:len(camera.distortion)] = list(camera.distortion)[:5]
    u = np.concatenate([np.linspace(0, width - 1, 32), np.linspace(0, width - 1, 32), np.zeros(32),
                        np.full(32, width - 1.0)])
    v = np.concatenate([np.zeros(32), np.full(32, height - 1.0), np.linspace(0, height - 1, 32),
                        np.linspace(0, height - 1, 32)])
    x, y = (u - cx) / fx, (v - cy) / fy
    r2 = x * x + y * y
    name = str(camera.distortionModel).rsplit(".", 1)[-1]
    if name == "RADIAL_TANGENTIAL":  # OpenCV order: k1, k2, p1, p2, k3
        k1, k2, p1, p2, k3 = d
        radial = 1 + k1 * r2 + k2 * r2**2 + k3 * r2**3
        xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
        yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    elif name == "EQUIDISTANT":  # Kannala-Brandt: k1..k4
        r = np.sqrt(r2)
        theta = np.arctan(r)
        theta_d = theta * (1 + d[0] * theta**2 + d[1] * theta**4 + d[2] * theta**6 + d[3] * theta**8)
        scale = np.where(r > 1e-12, theta_d / np.maximum(r, 1e-12), 1.0)
        xd, yd = x * scale, y * scale
    else:
        return 0.0
    return float(np.max(np.hypot((xd - x) * fx, (yd - y) * fy)))
