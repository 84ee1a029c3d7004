"""Our HDF5 recording: events, anchor frames, intrinsics, poses, trajectory and metadata in one file.

Layout (format ``edmcgs.recording``, version 1)::

    /                  attrs: format, format_version, width, height, sensor, metadata (JSON text),
                              contrast_threshold (only when known)
    /events/t          int64  [N]  µs, non-decreasing    (chunked, resizable: replays read lazily)
    /events/x, /y      uint16 [N]
    /events/p          int8   [N]  ±1
    /anchors/t_us      int64  [F]  strictly increasing
    /anchors/images    uint8  [F, H, W, C]  C = 1 grey or 3 RGB, H x W = the event resolution
    /anchors/poses     float64 [F, 4, 4]  camera-to-world, OpenCV convention   (optional)
    /held_out/...      same three as /anchors                                   (optional group)
    /intrinsics        float64 [4]  fx, fy, cx, cy in pixels                    (optional)
    /trajectory/t_us   int64  [T],  /trajectory/c2w  float64 [T, 4, 4]          (optional group)
    /imu/t             int64  [K]  µs, non-decreasing                           (optional group)
    /imu/accel         float32 [K, 3]  g;  /imu/gyro  float32 [K, 3]  degrees/s; /imu/temperature
                       float32 [K]  °C: the sensor layer's IMU_DTYPE (dv's units), in the axes the
                       metadata's "imu" entry states
    /novel_views/...   same three as /anchors: frames of a second camera, its poses required (optional
                       group; e.g. held-out views from another viewpoint, scored like held-out frames)
    /points/xyz        float64 [P, 3]  3D points of the static scene in the poses' world frame, e.g.
                       structure from motion's (``--poses auto``)                  (optional group)
    /points/colors     uint8  [P, C]  their colours, C the frames' channels

The optional groups are additions within version 1: a reader that predates them ignores them, and a
file without them reads as before (``imu``, ``novel_views`` and ``points_xyz`` None).

Files are written atomically (temporary file, fsync, rename) and the ``format`` attribute is written
last, so an interrupted write never leaves a file that reads as a complete recording.
``write_recording`` writes a whole ``Recording``; ``RecordingWriter`` streams one (``edmcgs record``).
``read_recording`` loads a whole file; ``RecordingFile`` opens one lazily (the HDF5 replay).
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path

import h5py
import numpy as np

from edmcgs.atomic import atomic_output, ensure_room
from edmcgs.errors import EdmcgsError, InvalidInputError, RecordingError, ReplayFormatError, translated
from edmcgs.sensor.events import Events
from edmcgs.sensor.files.event_file import FileEvents
from edmcgs.sensor.frames import Frames
from edmcgs.sensor.imu import IMU_DTYPE

FORMAT_NAME = "edmcgs.recording"
FORMAT_VERSION = 1
EVENT_CHUNK = 1 << 18  # events per HDF5 chunk: 3.25 MB over the four columns, one read per replay step


# ------------------------------------------------- validation shared by the dataclass and the writer

def _check_resolution(width, height) -> tuple[int, int]:
    if isinstance(width, bool) or isinstance(height, bool) or int(width) != width or int(height) != height:
        raise InvalidInputError(f"width and height must be integers, got {width!r} x {height!r}")
    if not (0 < int(width) <= 65536 and 0 < int(height) <= 65536):
        raise InvalidInputError(f"resolution must be within 1..65536, got {width} x {height}")
    return int(width), int(height)


def _check_events_in(events: Events | FileEvents, width: int, height: int, what: str = "events") -> None:
    if isinstance(events, FileEvents):
        return  # a file's: checked as each block is read (``RecordingFile.read_events``)
    if not isinstance(events, Events):
        raise InvalidInputError(f"{what} must be an Events batch, got {type(events).__name__}")
    if len(events) and (int(events.x.max()) >= width or int(events.y.max()) >= height):
        raise InvalidInputError(
            f"{what} reach x={events.x.max()}, y={events.y.max()}, outside the {width}x{height} resolution")


def _check_frames_in(frames: Frames | None, width: int, height: int, what: str) -> None:
    if frames is None:
        return
    if not isinstance(frames, Frames):
        raise InvalidInputError(f"{what} must be Frames, got {type(frames).__name__}")
    if (frames.width, frames.height) != (width, height):
        raise InvalidInputError(
            f"{what} are {frames.width}x{frames.height} but the recording is {width}x{height} "
            "(the event camera and the frame camera are the same camera)")


def _check_intrinsics(intrinsics) -> np.ndarray | None:
    if intrinsics is None:
        return None
    k = np.asarray(intrinsics, dtype=np.float64)
    if k.shape != (4,) or not np.isfinite(k).all() or k[0] <= 0 or k[1] <= 0:
        raise InvalidInputError(f"intrinsics must be 4 finite numbers fx, fy > 0, cx, cy; got {intrinsics!r}")
    return k


def _check_trajectory(t_us, c2w) -> tuple[np.ndarray | None, np.ndarray | None]:
    if t_us is None and c2w is None:
        return None, None
    if t_us is None or c2w is None:
        raise InvalidInputError("trajectory_t_us and trajectory_c2w must be given together")
    t_us, c2w = np.asarray(t_us), np.asarray(c2w, dtype=np.float64)
    if t_us.ndim != 1 or t_us.dtype.kind not in "iu" or len(t_us) == 0:
        raise InvalidInputError(
            f"trajectory_t_us must be a non-empty 1-D integer array, got {t_us.dtype} {t_us.shape}")
    if np.any(np.diff(t_us.astype(np.int64)) <= 0):
        raise InvalidInputError("trajectory_t_us must be strictly increasing")
    if c2w.shape != (len(t_us), 4, 4) or not np.isfinite(c2w).all():
        raise InvalidInputError(f"trajectory_c2w must be finite [{len(t_us)}, 4, 4], got {c2w.shape}")
    return t_us.astype(np.int64), c2w


def _check_imu(imu) -> np.ndarray | None:
    if imu is None:
        return None
    if not isinstance(imu, np.ndarray) or imu.dtype != IMU_DTYPE or imu.ndim != 1:
        raise InvalidInputError(f"imu must be a 1-D IMU_DTYPE array, got {getattr(imu, 'dtype', type(imu))}")
    if len(imu) and np.any(np.diff(imu["t"]) < 0):
        raise InvalidInputError("imu times must be non-decreasing")
    if not all(np.isfinite(imu[name]).all() for name in ("accel", "gyro", "temperature")):
        raise InvalidInputError("imu samples hold NaN or Inf")
    return imu


def _check_novel_views(frames, width: int, height: int) -> Frames | None:
    _check_frames_in(frames, width, height, "novel_views")
    if frames is not None and len(frames) and frames.poses is None:
        raise InvalidInputError("novel_views need their poses (they are views from another camera)")
    return frames


def _check_points(xyz, colors) -> tuple[np.ndarray | None, np.ndarray | None]:
    if xyz is None and colors is None:
        return None, None
    if xyz is None or colors is None:
        raise InvalidInputError("points_xyz and points_colors must be given together")
    xyz, colors = np.asarray(xyz, dtype=np.float64), np.asarray(colors)
    if xyz.ndim != 2 or xyz.shape[1] != 3 or not np.isfinite(xyz).all():
        raise InvalidInputError(f"points_xyz must be finite [P, 3], got {xyz.shape}")
    if colors.dtype != np.uint8 or colors.shape not in ((len(xyz), 1), (len(xyz), 3)):
        raise InvalidInputError(f"points_colors must be uint8 [{len(xyz)}, 1 | 3], got {colors.dtype} "
                                f"{colors.shape}")
    return xyz, colors


def _check_threshold(c) -> float | None:
    if c is None:
        return None
    c = float(c)
    if not np.isfinite(c) or c <= 0:
        raise InvalidInputError(f"contrast_threshold must be a finite positive number, got {c}")
    return c


def _metadata_json(metadata) -> str:
    if not isinstance(metadata, dict):
        raise InvalidInputError(f"metadata must be a dict, got {type(metadata).__name__}")
    try:
        return json.dumps(metadata, allow_nan=False, sort_keys=True)
    except (TypeError, ValueError) as exc:
        raise InvalidInputError(f"metadata must be JSON-serialisable (no NaN): {exc}") from exc


@dataclass
class Recording:
    """A whole recording in memory (see the module docstring for the file layout)."""

    width: int
    """Event (and frame) resolution, pixels."""
    height: int
    events: Events | FileEvents
    """All events; absolute Unix-epoch µs for real sensors, any int64 µs origin for synthetic data (or
    those left in the recording's file: ``read_recording(..., lazy_events=True)``)."""
    anchors: Frames
    """The sparse RGB/APS frames, with their poses when known."""
    held_out: Frames | None = None
    """Ground-truth frames at intermediate times, for evaluation only."""
    intrinsics: np.ndarray | None = None
    """float64 [4]: fx, fy, cx, cy in pixels at width x height."""
    trajectory_t_us: np.ndarray | None = None
    """int64 [T]: times of the continuous camera trajectory samples."""
    trajectory_c2w: np.ndarray | None = None
    """float64 [T, 4, 4]: camera-to-world poses at trajectory_t_us."""
    contrast_threshold: float | None = None
    """Event contrast threshold C (log intensity), when known."""
    sensor: str = "unknown"
    """Camera name, e.g. "DAVIS346_00000499" or "simulated"."""
    metadata: dict = field(default_factory=dict)
    """JSON-able extras: scene, simulator settings, seed, source file ..."""
    imu: np.ndarray | None = None
    """IMU_DTYPE [K] samples (g, degrees/s), when the recording has them."""
    novel_views: Frames | None = None
    """Frames of a second camera, with their poses (same size and intrinsics), for evaluation only."""
    points_xyz: np.ndarray | None = None
    """float64 [P, 3]: 3D points of the static scene in the world frame of the poses (structure from
    motion's, ``--poses auto``); None: none known."""
    points_colors: np.ndarray | None = None
    """uint8 [P, C]: their colours (C 1 or 3)."""

    def __post_init__(self) -> None:
        self.width, self.height = _check_resolution(self.width, self.height)
        _check_events_in(self.events, self.width, self.height)
        if self.anchors is None:
            raise InvalidInputError("anchors are required (use Frames.empty(height, width) for none)")
        _check_frames_in(self.anchors, self.width, self.height, "anchors")
        _check_frames_in(self.held_out, self.width, self.height, "held_out")
        self.intrinsics = _check_intrinsics(self.intrinsics)
        self.trajectory_t_us, self.trajectory_c2w = _check_trajectory(self.trajectory_t_us,
                                                                      self.trajectory_c2w)
        self.contrast_threshold = _check_threshold(self.contrast_threshold)
        self.imu = _check_imu(self.imu)
        self.novel_views = _check_novel_views(self.novel_views, self.width, self.height)
        self.points_xyz, self.points_colors = _check_points(self.points_xyz, self.points_colors)
        if not isinstance(self.sensor, str):
            raise InvalidInputError(f"sensor must be a string, got {type(self.sensor).__name__}")
        _metadata_json(self.metadata)

    @property
    def t_range_us(self) -> tuple[int, int] | None:
        """(first, last) time over events and anchors, or None when both are empty."""
        ends = [v for v in (self.events.t_start, self.events.t_end) if v is not None]
        if len(self.anchors):
            ends += [int(self.anchors.t_us[0]), int(self.anchors.t_us[-1])]
        return (min(ends), max(ends)) if ends else None


# ---------------------------------------------------------------- writing

def _create_frames_group(f: h5py.File, name: str, height: int, width: int, channels: int, poses: bool):
    g = f.create_group(name)
    g.create_dataset("t_us", shape=(0,), maxshape=(None,), dtype=np.int64, chunks=(1024,))
    g.create_dataset("images", shape=(0, height, width, channels), maxshape=(None, height, width, channels),
                     dtype=np.uint8, chunks=(1, height, width, channels), compression="gzip",
                     compression_opts=4, shuffle=True, fletcher32=True)
    if poses:
        g.create_dataset("poses", shape=(0, 4, 4), maxshape=(None, 4, 4), dtype=np.float64,
                         chunks=(256, 4, 4))
    return g


def _append(ds: h5py.Dataset, values: np.ndarray) -> None:
    n = ds.shape[0]
    ds.resize(n + len(values), axis=0)
    ds[n:] = values


class RecordingWriter:
    """Stream a recording to ``path`` atomically: nothing appears at ``path`` until ``finish()``.

    Use as a context manager: leaving the block normally finishes the file, an exception removes it.
    ``compression``: None (fastest replay) or an h5py filter name such as "lzf" for the event columns.
    """

    def __init__(self, path: str | os.PathLike, *, width: int, height: int, sensor: str = "unknown",
                 compression: str | None = None) -> None:
        self.path = Path(path)
        self.width, self.height = _check_resolution(width, height)
        if not isinstance(sensor, str):
            raise InvalidInputError(f"sensor must be a string, got {type(sensor).__name__}")
        self.sensor = sensor
        self._atomic = atomic_output(self.path, RecordingError)
        tmp = self._atomic.__enter__()
        try:
            self._f = h5py.File(tmp, "w", libver="latest")
            ev = self._f.create_group("events")
            # fletcher32: a flipped bit in a chunk is a read error, not a silently wrong event
            opts = {"compression": compression, "shuffle": compression is not None, "fletcher32": True}
            for name, dtype in (("t", np.int64), ("x", np.uint16), ("y", np.uint16), ("p", np.int8)):
                ev.create_dataset(name, shape=(0,), maxshape=(None,), dtype=dtype, chunks=(EVENT_CHUNK,),
                                  **opts)
        except BaseException as exc:
            self._atomic.__exit__(type(exc), exc, exc.__traceback__)
            raise RecordingError(f"cannot create {self.path}: {exc}") from exc
        self._last_t: int | None = None
        self._last_anchor_t: int | None = None
        self._anchors = None
        self._anchor_poses: bool | None = None
        self._done = False
        self.n_events = 0
        self.n_anchors = 0

    def append_events(self, events: Events) -> None:
        """Append a batch; it must start no earlier than the previous batch ended."""
        self._check_open()
        _check_events_in(events, self.width, self.height)
        if not len(events):
            return
        if self._last_t is not None and events.t[0] < self._last_t:
            raise InvalidInputError(
                f"events go back in time: batch starts at {events.t[0]} µs, "
                f"previous ended at {self._last_t} µs")
        ensure_room(self.path, 13 * len(events))
        g = self._f["events"]
        for c in "txyp":
            _append(g[c], getattr(events, c))
        self._last_t = int(events.t[-1])
        self.n_events += len(events)

    def append_anchors(self, frames: Frames) -> None:
        """Append anchor frames, later than any appended before; all with poses or all without."""
        self._check_open()
        _check_frames_in(frames, self.width, self.height, "anchors")
        if not len(frames):
            return
        if self._anchors is None:
            self._anchors = _create_frames_group(self._f, "anchors", self.height, self.width, frames.channels,
                                                 frames.poses is not None)
            self._anchor_poses = frames.poses is not None
        if frames.channels != self._anchors["images"].shape[3]:
            raise InvalidInputError(f"anchors have {frames.channels} channels, earlier ones had "
                                    f"{self._anchors['images'].shape[3]}")
        if (frames.poses is not None) != self._anchor_poses:
            raise InvalidInputError("anchors: some batches have poses and some do not")
        if self._last_anchor_t is not None and frames.t_us[0] <= self._last_anchor_t:
            raise InvalidInputError(f"anchor at {frames.t_us[0]} µs is not after the previous one "
                                    f"({self._last_anchor_t} µs)")
        ensure_room(self.path, frames.images.nbytes)
        _append(self._anchors["t_us"], frames.t_us)
        _append(self._anchors["images"], frames.images)
        if frames.poses is not None:
            _append(self._anchors["poses"], frames.poses)
        self._last_anchor_t = int(frames.t_us[-1])
        self.n_anchors += len(frames)

    def finish(self, *, held_out: Frames | None = None, intrinsics=None, trajectory_t_us=None,
               trajectory_c2w=None, contrast_threshold: float | None = None,
               metadata: dict | None = None, imu: np.ndarray | None = None,
               novel_views: Frames | None = None, points_xyz=None, points_colors=None) -> Path:
        """Write the remaining parts, then close, fsync and rename into place. Returns the path."""
        self._check_open()
        _check_frames_in(held_out, self.width, self.height, "held_out")
        imu = _check_imu(imu)
        novel_views = _check_novel_views(novel_views, self.width, self.height)
        points_xyz, points_colors = _check_points(points_xyz, points_colors)
        intrinsics = _check_intrinsics(intrinsics)
        traj_t, traj_c2w = _check_trajectory(trajectory_t_us, trajectory_c2w)
        contrast_threshold = _check_threshold(contrast_threshold)
        meta = _metadata_json({} if metadata is None else metadata)
        try:
            ensure_room(self.path, 0 if held_out is None else held_out.images.nbytes)
            f = self._f
            if self._anchors is None:
                _create_frames_group(f, "anchors", self.height, self.width, 1, False)
            for name, frames in (("held_out", held_out), ("novel_views", novel_views)):
                if frames is None:
                    continue
                g = _create_frames_group(f, name, self.height, self.width, frames.channels,
                                         frames.poses is not None)
                _append(g["t_us"], frames.t_us)
                _append(g["images"], frames.images)
                if frames.poses is not None:
                    _append(g["poses"], frames.poses)
            if imu is not None:
                g = f.create_group("imu")
                for name in IMU_DTYPE.names:
                    g.create_dataset(name, data=np.ascontiguousarray(imu[name]))
            if points_xyz is not None:
                g = f.create_group("points")
                g.create_dataset("xyz", data=points_xyz)
                g.create_dataset("colors", data=points_colors)
            if intrinsics is not None:
                f.create_dataset("intrinsics", data=intrinsics)
            if traj_t is not None:
                g = f.create_group("trajectory")
                g.create_dataset("t_us", data=traj_t)
                g.create_dataset("c2w", data=traj_c2w)
            f.attrs["width"] = self.width
            f.attrs["height"] = self.height
            f.attrs["sensor"] = self.sensor
            f.attrs["metadata"] = meta
            if contrast_threshold is not None:
                f.attrs["contrast_threshold"] = contrast_threshold
            f.attrs["format_version"] = FORMAT_VERSION
            f.attrs["format"] = FORMAT_NAME  # last: its presence marks a complete file
            f.close()
            self._done = True
            self._atomic.__exit__(None, None, None)
        except BaseException as exc:
            self.abort(exc)
            if not isinstance(exc, Exception) or isinstance(exc, EdmcgsError):
                raise
            raise RecordingError(f"writing {self.path} failed: {exc}") from exc
        return self.path

    def abort(self, exc: BaseException | None = None) -> None:
        """Discard the temporary file; nothing is left at ``path``."""
        if self._done:
            return
        self._done = True
        try:
            self._f.close()
        finally:
            err = exc if exc is not None else RecordingError("recording aborted")
            try:
                self._atomic.__exit__(type(err), err, err.__traceback__)
            except BaseException as raised:
                if raised is not err:
                    raise

    def _check_open(self) -> None:
        if self._done:
            raise RecordingError(f"recording {self.path} is already finished or aborted")

    def __enter__(self) -> RecordingWriter:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc is not None:
            self.abort(exc)
        elif not self._done:
            self.finish()


def write_recording(path: str | os.PathLike, rec: Recording, *, compression: str | None = None) -> Path:
    """Write ``rec`` to ``path`` atomically (temporary file, fsync, rename). Returns the path."""
    if not isinstance(rec, Recording):
        raise InvalidInputError(f"rec must be a Recording, got {type(rec).__name__}")
    with RecordingWriter(path, width=rec.width, height=rec.height, sensor=rec.sensor,
                         compression=compression) as w:
        for i in range(0, len(rec.events), 1 << 22):
            w.append_events(rec.events[i:i + (1 << 22)])
        w.append_anchors(rec.anchors)
        return w.finish(held_out=rec.held_out, intrinsics=rec.intrinsics, trajectory_t_us=rec.trajectory_t_us,
                        trajectory_c2w=rec.trajectory_c2w, contrast_threshold=rec.contrast_threshold,
                        metadata=rec.metadata, imu=rec.imu, novel_views=rec.novel_views,
                        points_xyz=rec.points_xyz, points_colors=rec.points_colors)


# ---------------------------------------------------------------- reading

def _keys(f: h5py.Group) -> list[str]:
    """Every dataset and group path in ``f`` (for error messages)."""
    names: list[str] = []
    f.visit(names.append)
    return names


def open_hdf5(path: Path) -> h5py.File:
    """``path`` opened read-only; ``ReplayFormatError`` when it is missing or not HDF5."""
    if not path.is_file():
        raise ReplayFormatError(f"{path}: no such file")
    try:
        return h5py.File(path, "r")
    except OSError as exc:
        raise ReplayFormatError(f"{path}: not a readable HDF5 file (truncated or corrupt?): {exc}") from exc


def is_recording(f: h5py.File) -> bool:
    """Whether an open HDF5 file claims to be our format (complete or newer)."""
    return f.attrs.get("format") == FORMAT_NAME


class RecordingFile:
    """An open recording, read lazily. Validates the structure on open; reads arrays on demand."""

    def __init__(self, path: str | os.PathLike) -> None:
        self.path = Path(path)
        self._f = open_hdf5(self.path)
        try:
            self._validate()
        except BaseException:
            self._f.close()
            raise

    def _fail(self, what: str) -> ReplayFormatError:
        return ReplayFormatError(f"{self.path}: {what}")

    def _validate(self) -> None:
        f = self._f
        with translated((OSError, KeyError, ValueError, TypeError, InvalidInputError),
                        lambda exc: self._fail(f"corrupt recording: {exc}"), keep=ReplayFormatError):
            fmt = f.attrs.get("format")
            if fmt != FORMAT_NAME:
                raise self._fail(
                    f"not an edmcgs recording (attribute format={fmt!r}, expected {FORMAT_NAME!r}; "
                    f"an interrupted write also lacks it); keys found: {_keys(f)[:20]}")
            version = int(f.attrs.get("format_version", -1))
            if version > FORMAT_VERSION:
                raise self._fail(f"written by a newer edmcgs (format version {version}; this one reads "
                                 f"<= {FORMAT_VERSION})")
            if version < 1:
                raise self._fail(f"bad format_version {version}")
            self.width, self.height = _check_resolution(f.attrs["width"], f.attrs["height"])
            self.sensor = str(f.attrs.get("sensor", "unknown"))
            self.metadata = json.loads(f.attrs.get("metadata", "{}"))
            c = f.attrs.get("contrast_threshold")
            self.contrast_threshold = None if c is None else float(c)
            want = {"t": np.int64, "x": np.uint16, "y": np.uint16, "p": np.int8}
            cols = {}
            for name, dtype in want.items():
                ds = f.get(f"events/{name}")
                if not isinstance(ds, h5py.Dataset) or ds.ndim != 1 or ds.dtype != dtype:
                    raise self._fail(f"events/{name} missing or not a 1-D {np.dtype(dtype)} dataset")
                cols[name] = ds
            if len({len(d) for d in cols.values()}) != 1:
                raise self._fail(f"event columns differ in length: { {k: len(d) for k, d in cols.items()} }")
            self.event_columns: dict[str, h5py.Dataset] = cols
            self.n_events = len(cols["t"])
            for group in ("anchors", "held_out", "novel_views"):
                if group in f:
                    self._validate_frames(group)
            if "imu" in f:
                self._validate_imu()
            if "points" in f:
                self._validate_points()
            if "anchors" not in f:
                raise self._fail("anchors group missing")

    def _validate_frames(self, group: str) -> None:
        g = self._f[group]
        t, img = g.get("t_us"), g.get("images")
        if not isinstance(t, h5py.Dataset) or not isinstance(img, h5py.Dataset):
            raise self._fail(f"{group} lacks t_us or images")
        if img.ndim != 4 or img.shape[1:3] != (self.height, self.width) or len(img) != len(t):
            raise self._fail(f"{group}/images has shape {img.shape}, expected [{len(t)}, {self.height}, "
                             f"{self.width}, C]")
        if "poses" in g and g["poses"].shape != (len(t), 4, 4):
            raise self._fail(f"{group}/poses has shape {g['poses'].shape}, expected [{len(t)}, 4, 4]")

    def _validate_imu(self) -> None:
        g = self._f["imu"]
        shapes = {name: (g[name].shape if isinstance(g.get(name), h5py.Dataset) else None)
                  for name in IMU_DTYPE.names}
        k = shapes["t"][0] if shapes["t"] is not None and len(shapes["t"]) == 1 else -1
        want = {"t": (k,), "accel": (k, 3), "gyro": (k, 3), "temperature": (k,)}
        if k < 0 or shapes != want:
            raise self._fail(f"imu group's datasets have shapes {shapes}, expected {want}")

    def _validate_points(self) -> None:
        g = self._f["points"]
        xyz, colors = g.get("xyz"), g.get("colors")
        if not isinstance(xyz, h5py.Dataset) or not isinstance(colors, h5py.Dataset) or xyz.ndim != 2 \
                or xyz.shape[1:] != (3,) or colors.shape not in ((len(xyz), 1), (len(xyz), 3)):
            raise self._fail(f"points group's xyz and colors have shapes "
                             f"{getattr(xyz, 'shape', None)} and {getattr(colors, 'shape', None)}, expected "
                             "[P, 3] and [P, 1 | 3]")

    def points(self) -> tuple[np.ndarray | None, np.ndarray | None]:
        """(xyz float64 [P, 3], colors uint8 [P, C]) of the static scene's points; (None, None) when the
        file has none."""
        if "points" not in self._f:
            return None, None
        g = self._f["points"]
        return self._read("points", lambda: _check_points(g["xyz"][:], g["colors"][:]))

    def imu(self) -> np.ndarray | None:
        """The IMU samples (IMU_DTYPE [K]; None when the file has none)."""
        if "imu" not in self._f:
            return None
        g = self._f["imu"]

        def load():
            out = np.empty(len(g["t"]), IMU_DTYPE)
            for name in IMU_DTYPE.names:
                out[name] = g[name][:]
            return _check_imu(out)

        return self._read("imu", load)

    def _read(self, what: str, fn):
        # InvalidInputError is translated: what we read fails the checks, the file is corrupt.
        with translated((OSError, KeyError, ValueError, InvalidInputError),
                        lambda exc: self._fail(f"cannot read {what} (truncated or corrupt?): {exc}"),
                        keep=ReplayFormatError):
            return fn()

    def read_event_columns(self, i0: int, i1: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Raw columns t, x, y, p for events [i0, i1) (unvalidated: the caller validates)."""
        c = self.event_columns
        return self._read(f"events [{i0}, {i1})", lambda: tuple(c[k][i0:i1] for k in "txyp"))

    def read_times(self, i0: int, i1: int, step: int = 1) -> np.ndarray:
        """int64 times of events [i0, i1), every ``step``-th (a time index's pass over the file)."""
        column = self.event_columns["t"]
        return self._read(f"events/t [{i0}, {i1})", lambda: np.asarray(column[i0:i1:step], np.int64))

    def events(self) -> FileEvents:
        """The events left in the file, read a window at a time (``event_file.FileEvents``)."""
        return FileEvents(self)

    def read_events(self, i0: int = 0, i1: int | None = None) -> Events:
        """Events [i0, i1), validated (strict: a file breaking the contract raises ReplayFormatError)."""
        i1 = self.n_events if i1 is None else i1
        cols = self.read_event_columns(i0, i1)
        ev = self._read("events", lambda: Events(*cols))
        self._read("events", lambda: _check_events_in(ev, self.width, self.height))
        return ev

    def frames(self, group: str = "anchors") -> Frames | None:
        """All frames of ``anchors``, ``held_out`` or ``novel_views`` (None when the group is absent)."""
        if group not in self._f:
            return None
        g = self._f[group]
        return self._read(group, lambda: Frames(g["t_us"][:], g["images"][:],
                                                g["poses"][:] if "poses" in g else None))

    def frame_times(self, group: str = "anchors") -> np.ndarray:
        return self._read(f"{group}/t_us", lambda: self._f[group]["t_us"][:].astype(np.int64))

    def frame_images(self, i0: int, i1: int, group: str = "anchors") -> np.ndarray:
        return self._read(f"{group}/images", lambda: self._f[group]["images"][i0:i1])

    def intrinsics(self) -> np.ndarray | None:
        """float64 [4] fx, fy, cx, cy, when stored."""
        f = self._f
        return self._read("intrinsics", lambda: f["intrinsics"][:] if "intrinsics" in f else None)

    def trajectory(self) -> tuple[np.ndarray | None, np.ndarray | None]:
        """(t_us [T], c2w [T, 4, 4]) of the camera, when stored."""
        f = self._f
        return self._read("trajectory", lambda: (f["trajectory/t_us"][:], f["trajectory/c2w"][:])
                          if "trajectory" in f else (None, None))

    def read(self, *, lazy_events: bool = False) -> Recording:
        """The whole recording in memory (with ``lazy_events``: all but its events, read from the open
        file when asked for: ``events()``)."""
        intr, traj, points = self.intrinsics(), self.trajectory(), self.points()
        return self._read("recording", lambda: Recording(
            width=self.width, height=self.height, events=self.events() if lazy_events else self.read_events(),
            anchors=self.frames("anchors"),
            held_out=self.frames("held_out"), intrinsics=intr, trajectory_t_us=traj[0],
            trajectory_c2w=traj[1], contrast_threshold=self.contrast_threshold, sensor=self.sensor,
            metadata=self.metadata, imu=self.imu(), novel_views=self.frames("novel_views"),
            points_xyz=points[0], points_colors=points[1]))

    def close(self) -> None:
        self._f.close()

    def __enter__(self) -> RecordingFile:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def read_recording(path: str | os.PathLike, *, lazy_events: bool = False) -> Recording:
    """Load a whole recording. Raises ReplayFormatError for a missing, truncated, corrupt or foreign file.
    lazy_events: its events stay in the file (``FileEvents``; the file stays open while they are used),
    so a recording of any length takes the memory of its frames."""
    f = RecordingFile(path)
    try:
        rec = f.read(lazy_events=lazy_events)
    except BaseException:
        f.close()
        raise
    if not lazy_events:
        f.close()
    return rec
