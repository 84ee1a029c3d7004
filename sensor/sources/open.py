"""Open a source from what a user typed: a live camera, or a recording in any format read here, told
apart by its content (magic bytes and headers), not by its name."""

from __future__ import annotations

import os

from edmcgs.errors import InvalidInputError, ReplayFormatError
from edmcgs.filekind import recording_kind
from edmcgs.sensor.sources.base import EventSource
from edmcgs.sensor.sources.pacing import Pacing


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
    """Which reader ``path`` needs, from its content (``edmcgs.filekind``): one of aedat4, jaer, prophesee,
    hdf5, rosbag, rpg. ``ReplayFormatError`` names the file, what it is, and what is read."""
    return recording_kind(path, error=ReplayFormatError)


def open_source(path: str | os.PathLike | None = None, *, live: bool = False, serial: str | None = None,
                pacing: Pacing | None = None, resolution: tuple[int, int] | None = None) -> EventSource:
    """``live=True``: the DAVIS on USB (``serial`` picks one). Otherwise a replay of ``path``, in any
    format of ``filekind.FORMATS`` (``detect_format``), played with ``pacing``; ``resolution`` (width,
    height) for files that do not state one (DSEC, v2e, some Prophesee and ROS files, the RPG layout
    without images)."""
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
