"""AEDAT 2.0 (jAER) and AEDAT 3.1 (cAER) replay: the DVS events of the DAVIS and DVS128 files recorded
before DV's AEDAT4, decoded here from iniVation's published layouts (no maintained Python reader decodes
them: evlib's reads 2.0 as timestamp-first DVS128 words and 3.1 without its packet headers).

- **AEDAT 2.0**: ``#`` header lines (``# AEChip: <jAER chip class>`` names the camera; where no line
  does, jAER's default file name, ``<chip>-<date>.aedat``, does), then big-endian (uint32 address, uint32
  µs timestamp) pairs. DAVIS: a DVS event has address bits 31 and 10 clear, y in bits 22-30, x in bits
  12-21, polarity bit 11 (1 = ON); DVS128 (jAER's ``DVS128.Extractor``): bit 15 (a sync event) clear,
  y in bits 8-14, x in bits 1-7 mirrored (x = 127 - raw), polarity bit 0 (0 = ON). jAER's origin is the
  lower left: y is flipped to the upper left. The 32-bit timestamps wrap every 71.6 minutes; each wrap
  is undone.
- **AEDAT 3.1**: ``#`` header lines to ``#!END-HEADER`` (``#Source N: <camera>``), then packets: a 28-byte
  little-endian header (type, source, event size, timestamp offset, timestamp overflow, capacity,
  number, valid) and ``capacity`` events. Polarity events (type 1, 8 bytes): uint32 data (bit 0 valid,
  bit 1 polarity, y in bits 2-16, x in bits 17-31) and int32 µs timestamp, extended by the overflow.

APS samples and frames, IMU samples and special events are skipped (only DVS events are read). The
resolution comes from the camera's name, else ``resolution``, else the smallest sensor holding every
event (one pass). Files are read forward in blocks (never whole).
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from edmcgs.errors import InvalidInputError, ReplayFormatError
from edmcgs.sensor.sources.base import StreamInfo
from edmcgs.sensor.sources.pacing import Pacing
from edmcgs.sensor.sources.replay import Chunk, Replay

# camera-name fragment (lower case) -> (width, height, address layout of AEDAT 2.0)
_CAMERAS = (("dvs128", 128, 128, "dvs128"), ("tmpdiff128", 128, 128, "dvs128"),
            ("davis240", 240, 180, "davis"), ("davis346", 346, 260, "davis"),
            ("davis640", 640, 480, "davis"), ("davis128", 128, 128, "davis"), ("davis208", 208, 192, "davis"))
_RECORDS = 1 << 20  # AEDAT 2.0 records per block (8 MB)
_PACKET = np.dtype([("type", "<i2"), ("source", "<i2"), ("size", "<i4"), ("ts_offset", "<i4"),
                    ("ts_overflow", "<i4"), ("capacity", "<i4"), ("number", "<i4"), ("valid", "<i4")])
_POLARITY = 1


class JaerReplay(Replay):
    """Replay a jAER AEDAT 2.0 or cAER AEDAT 3.1 file (see the module docstring); ``resolution``
    (width, height) for a camera whose name says none."""

    def __init__(self, path: str | os.PathLike, pacing: Pacing | None = None, *,
                 resolution: tuple[int, int] | None = None, **kwargs) -> None:
        super().__init__(pacing, **kwargs)
        self.path = Path(path)
        if not self.path.is_file():
            raise ReplayFormatError(f"{self.path}: no such file")
        self._version, self._data_at, camera = self._header()
        if not camera and self._version == 2:  # jAER names a file for its chip unless told otherwise
            camera = self.path.name.split("-", 1)[0]
        known = [c for c in _CAMERAS if c[0] in camera.lower().replace(" ", "")]
        self._layout = known[0][3] if known else "davis"
        if known:
            width, height = known[0][1:3]
        elif resolution is not None:
            if len(resolution) != 2 or min(resolution) <= 0:
                raise InvalidInputError(f"resolution must be (width, height) > 0, got {resolution!r}")
            width, height = (int(v) for v in resolution)
        elif self._version == 2:
            raise ReplayFormatError(f"{self.path}: unknown jAER chip {camera or '(none named)'}: its "
                                    "address layout is unknown; give the resolution (--resolution "
                                    "WIDTHxHEIGHT) to read it as a DAVIS")
        else:  # not stated: the smallest sensor that holds every event
            width = height = 1
            for _, x, y, _ in self._blocks(flip_height=None):
                width, height = max(width, int(x.max()) + 1), max(height, int(y.max()) + 1)
        self._height = height
        first = last = None
        for t, *_ in self._blocks(flip_height=height):
            first = int(t[0]) if first is None else first
            last = int(t[-1])
        version = "2.0" if self._version == 2 else "3.1"
        self._info = StreamInfo(width=width, height=height, has_frames=False, has_imu=False, live=False,
                                sensor=f"{camera or 'unknown camera'} (AEDAT {version})",
                                t_range_us=None if first is None else (first, last))

    def _fail(self, what: str) -> ReplayFormatError:
        return ReplayFormatError(f"{self.path}: {what} (truncated or corrupt AEDAT {self._version}?)")

    def _header(self) -> tuple[int, int, str]:
        """(major version, where the data starts, the camera's name)."""
        with open(self.path, "rb") as f:
            first = f.readline()
            version = 2 if first.startswith(b"#!AER-DAT2") else 3 if first.startswith(b"#!AER-DAT3") else 0
            if not version:
                raise ReplayFormatError(f"{self.path}: not AEDAT 2.0 / 3.1 (it starts with {first[:16]!r})")
            self._version = version
            camera, at = "", f.tell()
            while (line := f.readline()).startswith(b"#"):
                at = f.tell()
                text = line.decode("latin-1").strip()
                if version == 3 and text.startswith("#!END-HEADER"):
                    return version, at, camera
                key, _, value = text.lstrip("# ").partition(":")
                if key == "AEChip" or (version == 3 and key.startswith("Source") and not camera):
                    camera = value.strip().rsplit(".", 1)[-1]
            if version == 3:
                raise self._fail("no #!END-HEADER line")
        return version, at, camera

    def _blocks(self, flip_height: int | None) -> Iterator[tuple[np.ndarray, ...]]:
        """(t, x, y, p) of the DVS events, block by block, times unwrapped; y flipped (AEDAT 2.0) for
        ``flip_height`` rows."""
        yield from (self._blocks2(flip_height) if self._version == 2 else self._blocks3())

    def _blocks2(self, flip_height: int | None) -> Iterator[tuple[np.ndarray, ...]]:
        record = np.dtype([("a", ">u4"), ("t", ">u4")])
        wraps, previous = 0, None
        with open(self.path, "rb") as f:
            f.seek(self._data_at)
            while len(rows := np.fromfile(f, record, _RECORDS)):
                t = rows["t"].astype(np.int64)
                # a wrap: the 32-bit clock falls back by more than half its range
                steps = np.diff(t, prepend=t[0] if previous is None else previous)
                wrapped = np.cumsum(steps < -(1 << 31)) + wraps
                previous, wraps = int(t[-1]), int(wrapped[-1])
                t += wrapped << 32
                a = rows["a"]
                if self._layout == "dvs128":
                    keep = (a & 0x80008000) == 0
                    x, y, p = 127 - ((a >> 1) & 0x7F), (a >> 8) & 0x7F, 1 - (a & 1)
                else:
                    keep = (a & 0x80000400) == 0
                    x, y, p = (a >> 12) & 0x3FF, (a >> 22) & 0x1FF, (a >> 11) & 1
                if flip_height is not None:
                    y = flip_height - 1 - y.astype(np.int64)
                if keep.any():
                    yield t[keep], x[keep].astype(np.int64), y[keep].astype(np.int64), p[keep].astype(np.int8)

    def _blocks3(self) -> Iterator[tuple[np.ndarray, ...]]:
        with open(self.path, "rb") as f:
            f.seek(self._data_at)
            while len(raw := f.read(_PACKET.itemsize)):
                if len(raw) < _PACKET.itemsize:
                    raise self._fail(f"a packet header cut short at byte {f.tell() - len(raw)}")
                head = np.frombuffer(raw, _PACKET)[0]
                size, capacity = int(head["size"]), int(head["capacity"])
                if size <= 0 or capacity < 0 or not 0 <= head["number"] <= capacity:
                    raise self._fail(f"a bad packet header at byte {f.tell() - len(raw)}")
                body = f.read(size * capacity)
                if len(body) < size * capacity:
                    raise self._fail(f"a packet cut short at byte {f.tell() - len(body)}")
                if head["type"] != _POLARITY or head["number"] == 0:
                    continue
                if size != 8:
                    raise self._fail(f"polarity events of {size} bytes (8 expected)")
                rows = np.frombuffer(body, [("d", "<u4"), ("t", "<i4")], int(head["number"]))
                valid = (rows["d"] & 1) == 1
                d = rows["d"][valid]
                t = rows["t"][valid].astype(np.int64) | (np.int64(head["ts_overflow"]) << 31)
                if len(t):
                    yield (t, (d >> 17).astype(np.int64), ((d >> 2) & 0x7FFF).astype(np.int64),
                           ((d >> 1) & 1).astype(np.int8))

    def _chunks(self, begin_us: int) -> Iterator[Chunk]:
        for t, x, y, p in self._blocks(flip_height=self._height):
            if t[-1] < begin_us:
                continue
            # more events at the block's last time may follow in the next one
            yield Chunk(events=self._validated(t, x, y, p), frames=None, imu=None, horizon_us=int(t[-1]))
