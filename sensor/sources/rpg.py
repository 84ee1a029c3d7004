"""Replay of the RPG text layout (the Event Camera Dataset's): a folder of plain text files.

- ``events.txt``: ``t x y p`` per line, t in seconds, p 0 (OFF) or 1 (ON);
- ``images.txt`` (optional): ``t images/frame_00000000.png`` per line, the images beside it (grey or RGB);
- ``imu.txt`` (optional): ``t ax ay az gx gy gz`` (m/s², rad/s), converted to dv's units (g, degrees per
  second; no temperature: 0);
- ``groundtruth.txt`` (optional): ``t px py pz qx qy qz qw``, the camera-to-world trajectory;
- ``calib.txt`` (optional): ``fx fy cx cy [k1 k2 p1 p2 k3]``.

Seconds become int64 µs (rounded). The resolution is the images', else ``resolution``, else the smallest
sensor holding every event (one pass). ``events.txt`` is read forward in blocks (never whole); the other
files are small and read on open, the images one by one as the replay reaches them.
"""

from __future__ import annotations

import math
import os
import warnings
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from edmcgs.errors import InvalidInputError, PoseError, ReplayFormatError
from edmcgs.geometry import pose_from_quat, validate_pose
from edmcgs.sensor.frames import Frames
from edmcgs.sensor.imu import IMU_DTYPE
from edmcgs.sensor.sources.base import Extras, StreamInfo
from edmcgs.sensor.sources.pacing import Pacing
from edmcgs.sensor.sources.replay import Ahead, Chunk, Replay

_BLOCK = 1 << 24  # bytes of events.txt parsed at a time (about 600k events)
_G = 9.80665  # m/s² per g


def _us(seconds: np.ndarray) -> np.ndarray:
    return np.rint(seconds * 1e6).astype(np.int64)


class RpgReplay(Replay):
    """Replay a folder in the RPG text layout (see the module docstring), given as the folder or its
    ``events.txt``; ``resolution`` (width, height) for one without images."""

    def __init__(self, path: str | os.PathLike, pacing: Pacing | None = None, *,
                 resolution: tuple[int, int] | None = None, **kwargs) -> None:
        super().__init__(pacing, **kwargs)
        given = Path(path)
        self.path = given.parent if given.name == "events.txt" else given
        self._events_path = self.path / "events.txt"
        if not self._events_path.is_file():
            raise ReplayFormatError(f"{self.path}: no events.txt (the RPG layout's events)")
        self._image_t, self._image_files = self._images()
        imu = self._table("imu.txt", 7)
        self._imu = None
        if imu is not None:
            self._imu = np.zeros(len(imu), IMU_DTYPE)
            self._imu["t"], self._imu["accel"], self._imu["gyro"] = _us(imu[:, 0]), imu[:, 1:4] / _G, \
                np.degrees(imu[:, 4:7])
        frame_size = None
        if len(self._image_files):
            first = self._image(0)
            frame_size = (first.shape[1], first.shape[0])
        if frame_size is not None:
            width, height = frame_size
        elif resolution is not None:
            if len(resolution) != 2 or min(resolution) <= 0:
                raise InvalidInputError(f"resolution must be (width, height) > 0, got {resolution!r}")
            width, height = (int(v) for v in resolution)
        else:  # not stated: the smallest sensor that holds every event
            width = height = 1
            for _, x, y, _ in self._blocks():
                width, height = max(width, int(x.max()) + 1), max(height, int(y.max()) + 1)
        first = next(self._blocks(), None)
        times = [] if first is None else [int(first[0][0]), int(self._last_block()[0][-1])]
        for t in (self._image_t, None if self._imu is None else self._imu["t"]):
            if t is not None and len(t):
                times += [int(t[0]), int(t[-1])]
        self._extras = Extras(*self._calibration(), *self._groundtruth())
        self._info = StreamInfo(width=width, height=height, sensor=f"RPG text layout {self.path.name}",
                                has_frames=frame_size is not None, has_imu=self._imu is not None, live=False,
                                t_range_us=(min(times), max(times)) if times else None, frame_size=frame_size)

    # ------------------------------------------------------------------ the small files

    def _fail(self, name: str, what: str) -> ReplayFormatError:
        return ReplayFormatError(f"{self.path / name}: {what}")

    def _lines(self, name: str) -> list[tuple[int, list[str]]] | None:
        path = self.path / name
        if not path.is_file():
            return None
        try:
            text = path.read_text()
        except (OSError, UnicodeDecodeError) as exc:
            raise self._fail(name, f"cannot read it: {exc}") from exc
        return [(i, line.split()) for i, line in enumerate(text.splitlines(), 1)
                if line.strip() and not line.lstrip().startswith("#")]

    def _table(self, name: str, columns: int) -> np.ndarray | None:
        """A text file of ``columns`` numbers per line, time first and increasing; None when absent."""
        lines = self._lines(name)
        if lines is None:
            return None
        rows = []
        for number, fields in lines:
            try:
                values = [float(v) for v in fields]
            except ValueError:
                values = []
            if len(values) != columns or not all(math.isfinite(v) for v in values):
                raise self._fail(name, f"line {number}: expected {columns} numbers, got {' '.join(fields)!r}")
            rows.append(values)
        table = np.array(rows, np.float64).reshape(-1, columns)
        if np.any(np.diff(_us(table[:, 0])) <= 0):
            raise self._fail(name, "times must be strictly increasing (to the microsecond)")
        return table

    def _images(self) -> tuple[np.ndarray, list[Path]]:
        lines = self._lines("images.txt") or []
        times, files = [], []
        for number, fields in lines:
            try:
                t = float(fields[0])
            except (ValueError, IndexError):
                t = math.nan
            if len(fields) != 2 or not math.isfinite(t):
                raise self._fail("images.txt", f"line {number}: expected 't images/NAME.png', got "
                                               f"{' '.join(fields)!r}")
            times.append(t)
            files.append(self.path / fields[1])
        t_us = _us(np.array(times, np.float64))
        if np.any(np.diff(t_us) <= 0):
            raise self._fail("images.txt", "times must be strictly increasing (to the microsecond)")
        return t_us, files

    def _image(self, i: int) -> np.ndarray:
        from PIL import Image, UnidentifiedImageError

        try:
            with Image.open(self._image_files[i]) as im:
                img = np.asarray(im.convert("L" if im.mode in ("1", "L", "I", "I;16", "F") else "RGB"))
        except (OSError, UnidentifiedImageError) as exc:
            raise ReplayFormatError(f"{self._image_files[i]}: cannot read the image: {exc}") from exc
        return img[..., None] if img.ndim == 2 else img

    def _calibration(self) -> tuple[tuple | None, tuple | None]:
        lines = self._lines("calib.txt")
        if not lines:
            return None, None
        try:
            values = [float(v) for _, fields in lines for v in fields]
        except ValueError:
            values = []
        if len(values) < 4 or not all(math.isfinite(v) for v in values) or min(values[:2]) <= 0:
            raise self._fail("calib.txt", "expected 'fx fy cx cy [k1 k2 p1 p2 k3]' (fx, fy > 0)")
        distortion = tuple(values[4:]) if any(values[4:]) else None
        return tuple(values[:4]), distortion

    def _groundtruth(self) -> tuple[np.ndarray | None, np.ndarray | None]:
        table = self._table("groundtruth.txt", 8)
        if table is None:
            return None, None
        try:
            c2w = np.stack([validate_pose(pose_from_quat(r[1:4], [r[7], r[4], r[5], r[6]]),
                                          name=f"groundtruth.txt pose {i}") for i, r in enumerate(table)])
        except PoseError as exc:
            raise self._fail("groundtruth.txt", str(exc)) from exc
        return _us(table[:, 0]), c2w

    # ------------------------------------------------------------------ events.txt, forward

    def _parse(self, block: bytes, offset: int) -> tuple[np.ndarray, ...]:
        bad = self._fail("events.txt", f"the lines after byte {offset} are not 't x y p' numbers")
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")  # older numpy warns and stops at a bad number: counted below
                values = np.fromstring(block, dtype=np.float64, sep=" ")
        except ValueError as exc:
            raise bad from exc
        lines = block.count(b"\n") - block.count(b"\n\n")
        if values.size != 4 * lines or not np.isfinite(values).all():
            raise bad
        rows = values.reshape(-1, 4)
        x, y, p = rows[:, 1], rows[:, 2], rows[:, 3]
        if np.any((x != np.round(x)) | (y != np.round(y)) | ((p != 0) & (p != 1))):
            raise self._fail("events.txt", f"after byte {offset}: x and y must be integers, p 0 or 1")
        return _us(rows[:, 0]), x.astype(np.int64), y.astype(np.int64), p.astype(np.int8)

    def _blocks(self) -> Iterator[tuple[np.ndarray, ...]]:
        with open(self._events_path, "rb") as f:
            offset, rest = 0, b""
            while True:
                data = f.read(_BLOCK)
                block = rest + data
                if data and b"\n" in block:
                    cut = block.rindex(b"\n") + 1
                    block, rest = block[:cut], block[cut:]
                elif data:
                    rest = block
                    continue
                else:
                    rest = b""
                    if block and not block.endswith(b"\n"):
                        block += b"\n"
                if block.strip():
                    cols = self._parse(block, offset)
                    if len(cols[0]):
                        yield cols
                offset += len(block)
                if not data:
                    return

    def _last_block(self) -> tuple[np.ndarray, ...]:
        """The last lines of events.txt (for the time range, without reading it all)."""
        with open(self._events_path, "rb") as f:
            size = f.seek(0, os.SEEK_END)
            f.seek(max(0, size - 4096))
            tail = f.read().rstrip(b"\n").split(b"\n")[-1] + b"\n"
        return self._parse(tail, size - len(tail))

    def _chunks(self, begin_us: int) -> Iterator[Chunk]:
        frames = Ahead(((int(t), i) for i, t in enumerate(self._image_t)))
        imu_t = self._imu["t"] if self._imu is not None else np.empty(0, np.int64)
        imu = Ahead(((int(t), i) for i, t in enumerate(imu_t)))
        for t, x, y, p in self._blocks():
            horizon = int(t[-1])  # more events at t[-1] may follow
            if horizon < begin_us:
                continue
            yield self._chunk(self._validated(t, x, y, p), frames.until(horizon), imu.until(horizon), horizon)
        yield self._chunk(self._validated(*([np.empty(0, np.int64)] * 4)), frames.until(2**62),
                          imu.until(2**62), 2**62)

    def _chunk(self, events, frames: list, imu: list, horizon: int) -> Chunk:
        fr = None
        if frames:
            images = [self._image(i) for _, i in frames]
            try:
                fr = Frames([t for t, _ in frames], np.stack(images))
            except (InvalidInputError, ValueError) as exc:
                raise self._fail("images.txt", f"its images differ in size or kind: {exc}") from exc
        im = self._imu[[i for _, i in imu]] if imu else None
        return Chunk(events=events, frames=fr, imu=im, horizon_us=horizon)
