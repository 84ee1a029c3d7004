"""Prophesee RAW (EVT 2.0, 2.1, 3.0) and DAT replay, decoded by faery (``faery.events_stream_from_file``).

The file's ``% key value`` header says the encoding and, on most cameras, the sensor size (``geometry
WxH``, ``format EVT3;width=..;height=..``, or DAT's ``Width`` / ``Height``). Gen3 cameras (VGA) write no
size: 640 x 480 is taken from their plugin name; any other file without one needs ``resolution``.
Timestamps are the camera's µs since it started streaming. Trigger events are skipped. Files are read
forward packet by packet (never whole); opening one reads it once for its time range.
"""

from __future__ import annotations

import os
import re
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from edmcgs.errors import EdmcgsError, InvalidInputError, ReplayFormatError, translated
from edmcgs.sensor.sources.base import StreamInfo
from edmcgs.sensor.sources.pacing import Pacing
from edmcgs.sensor.sources.replay import Chunk, Replay

_HEADER_BYTES = 1 << 16
_VGA_PLUGINS = ("gen3", "gen31")  # Prophesee's Gen3 (640 x 480) HAL plugins, whose files state no size


def read_header(path: Path) -> dict[str, str]:
    """The ``% key value`` lines at the start of a Prophesee file (keys lower-cased)."""
    with open(path, "rb") as f:
        head = f.read(_HEADER_BYTES)
    header: dict[str, str] = {}
    for line in head.split(b"\n"):
        if not line.startswith(b"% "):
            break
        key, _, value = line[2:].decode("latin-1").strip().partition(" ")
        if key.lower() == "end":
            break
        header[key.lower()] = value.strip()
    return header


def is_raw(header: dict[str, str]) -> bool:
    """A RAW (EVT) header rather than a DAT one."""
    return "evt" in header or header.get("format", "").upper().startswith("EVT")


def stated_size(header: dict[str, str]) -> tuple[int, int] | None:
    """(width, height) as the header states it, if it does."""
    if m := re.fullmatch(r"(\d+)x(\d+)", header.get("geometry", "")):
        return int(m[1]), int(m[2])
    fields = dict(f.split("=", 1) for f in header.get("format", "").split(";")[1:] if "=" in f)
    if {"width", "height"} <= fields.keys():
        return int(fields["width"]), int(fields["height"])
    if header.get("width", "").isdigit() and header.get("height", "").isdigit():
        return int(header["width"]), int(header["height"])
    plugin = header.get("plugin_name", "").lower()
    if any(plugin.endswith(f"_{name}") or f"_{name}_" in plugin for name in _VGA_PLUGINS):
        return 640, 480
    return None


class PropheseeReplay(Replay):
    """Replay a Prophesee .raw (EVT 2.0 / 2.1 / 3.0) or .dat file; ``resolution`` (width, height) for a
    file whose header states no size."""

    def __init__(self, path: str | os.PathLike, pacing: Pacing | None = None, *,
                 resolution: tuple[int, int] | None = None, **kwargs) -> None:
        super().__init__(pacing, **kwargs)
        self.path = Path(path)
        if not self.path.is_file():
            raise ReplayFormatError(f"{self.path}: no such file")
        header = self._read("read the header", lambda: read_header(self.path))
        self._kind = "evt" if is_raw(header) else "dat"
        size = stated_size(header) or resolution
        if size is None:
            raise ReplayFormatError(f"{self.path}: its header states no sensor size (keys: "
                                    f"{sorted(header)}); give the resolution (--resolution WIDTHxHEIGHT)")
        if len(size) != 2 or min(size) <= 0:
            raise InvalidInputError(f"resolution must be (width, height) > 0, got {size!r}")
        self._size = (int(size[0]), int(size[1]))
        self._size = tuple(int(v) for v in self._stream().dimensions())  # the header's, as faery reads it
        first = last = None
        for packet in self._packets():
            first = int(packet["t"][0]) if first is None else first
            last = int(packet["t"][-1])
        self._info = StreamInfo(
            width=self._size[0], height=self._size[1], has_frames=False, has_imu=False, live=False,
            sensor=" ".join(filter(None, ["Prophesee", header.get("plugin_name", self._kind.upper()),
                                          header.get("serial_number")])),
            t_range_us=None if first is None else (first, last))

    def _read(self, what: str, fn):
        # faery says what is wrong in a plain Exception or a RuntimeError; ours pass through.
        def corrupt(exc: BaseException) -> ReplayFormatError:
            return ReplayFormatError(f"{self.path}: cannot {what} (not a Prophesee file, truncated or "
                                     f"corrupt?): {exc}")

        with translated((Exception,), corrupt, keep=(EdmcgsError,)):
            return fn()

    def _stream(self):
        import faery

        return self._read("open", lambda: faery.events_stream_from_file(
            self.path, dimensions_fallback=self._size, file_type=self._kind))

    def _packets(self) -> Iterator[np.ndarray]:
        packets = iter(self._stream())
        while (packet := self._read("read events", lambda: next(packets, None))) is not None:
            if len(packet):
                yield packet

    def _chunks(self, begin_us: int) -> Iterator[Chunk]:
        for packet in self._packets():
            if packet["t"][-1] < begin_us:
                continue
            # more events at the packet's last time may follow in the next one
            yield Chunk(events=self._validated(packet["t"], packet["x"], packet["y"], packet["on"]),
                        frames=None, imu=None, horizon_us=int(packet["t"][-1]))
