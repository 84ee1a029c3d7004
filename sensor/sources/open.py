"""Open a source from what a user typed: a live camera, or a recording in any format read here, told
apart by its content (magic bytes and headers), not by its name."""

from __future__ import annotations

import os
from pathlib import Path

from edmcgs.errors import InvalidInputError, ReplayFormatError
from edmcgs.sensor.sources.base import EventSource
from edmcgs.sensor.sources.pacing import Pacing

FORMATS = (
    "AEDAT4 (iniVation DV)",
    "AEDAT 2.0 / 3.1 (jAER, cAER)",
    "Prophesee RAW (EVT 2.0, 2.1, 3.0) and DAT",
    "HDF5 (edmcgs recording, DSEC, v2e)",
    "ROS 1 bag and ROS 2 bag (a folder with metadata.yaml, or its .db3 / .mcap)",
    "the RPG text layout (a folder with events.txt [images.txt, imu.txt, groundtruth.txt, calib.txt])",
)
"""What ``open_source`` reads, for messages."""

_MAGIC = (
    (b"#!AER-DAT4", "aedat4"),
    (b"#!AER-DAT2", "jaer"),
    (b"#!AER-DAT3", "jaer"),
    (b"\x89HDF\r\n\x1a\n", "hdf5"),
    (b"#ROSBAG V2.0", "rosbag"),
    (b"\x89MCAP", "rosbag"),
    (b"SQLite format 3\x00", "rosbag"),
    (b"% ", "prophesee"),
)


def parse_resolution(text: str | None) -> tuple[int, int] | None:
    """``WIDTHxHEIGHT`` (a ``--resolution`` flag) as (width, height); None passes through."""
    if text is None:
        return None
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise InvalidInputError(f"--resolution must look like 640x480, got {text!r}") from None
    return w, h


def detect_format(path: str | os.PathLike) -> str:
    """Which reader ``path`` needs, from its first bytes (a folder: from the files in it): one of aedat4,
    jaer, prophesee, hdf5, rosbag, rpg. ``ReplayFormatError`` names the file and what is read."""
    path = Path(path)
    if path.is_dir():
        if (path / "events.txt").is_file():
            return "rpg"
        if (path / "metadata.yaml").is_file():
            return "rosbag"
        raise ReplayFormatError(f"{path}: a folder without events.txt (the RPG layout) or metadata.yaml "
                                f"(a ROS 2 bag); recordings read here: {'; '.join(FORMATS)}")
    if not path.is_file():
        raise ReplayFormatError(f"{path}: no such file")
    if path.name == "events.txt":
        return "rpg"
    try:
        with open(path, "rb") as f:
            head = f.read(32)
    except OSError as exc:
        raise ReplayFormatError(f"{path}: cannot read it: {exc}") from exc
    for magic, name in _MAGIC:
        if head.startswith(magic):
            return name
    raise ReplayFormatError(f"{path}: not a recording read here (it starts with {head[:16]!r}); recordings "
                            f"read here: {'; '.join(FORMATS)}")


def open_source(path: str | os.PathLike | None = None, *, live: bool = False, serial: str | None = None,
                pacing: Pacing | None = None, resolution: tuple[int, int] | None = None) -> EventSource:
    """``live=True``: the DAVIS on USB (``serial`` picks one). Otherwise a replay of ``path``, in any
    format of ``FORMATS`` (``detect_format``), played with ``pacing``; ``resolution`` (width, height) for
    files that do not state one (DSEC, v2e, some Prophesee and ROS files, the RPG layout without images).
    """
    if live:
        if path is not None:
            raise InvalidInputError("give either a recording path or live=True, not both")
        from edmcgs.sensor.sources.davis import DavisSource

        return DavisSource(serial)
    if path is None:
        raise InvalidInputError("a recording path is required unless live=True")
    kind = detect_format(path)
    if kind == "aedat4":
        from edmcgs.sensor.sources.aedat import AedatReplay

        return AedatReplay(path, pacing)
    if kind == "hdf5":
        from edmcgs.sensor.sources.hdf5 import Hdf5Replay

        return Hdf5Replay(path, pacing, resolution=resolution)
    if kind == "prophesee":
        from edmcgs.sensor.sources.prophesee import PropheseeReplay

        return PropheseeReplay(path, pacing, resolution=resolution)
    if kind == "rosbag":
        from edmcgs.sensor.sources.rosbag import RosbagReplay

        return RosbagReplay(path, pacing, resolution=resolution)
    if kind == "rpg":
        from edmcgs.sensor.sources.rpg import RpgReplay

        return RpgReplay(path, pacing, resolution=resolution)
    from edmcgs.sensor.sources.jaer import JaerReplay

    return JaerReplay(path, pacing, resolution=resolution)
