"""Open a source from what a user typed: a live camera, an .aedat4 file or an HDF5 file."""

from __future__ import annotations

import os
from pathlib import Path

from edmcgs.errors import InvalidInputError
from edmcgs.sensor.sources.base import EventSource
from edmcgs.sensor.sources.pacing import Pacing

AEDAT_SUFFIXES = (".aedat4",)
HDF5_SUFFIXES = (".h5", ".hdf5")


def parse_resolution(text: str | None) -> tuple[int, int] | None:
    """``WIDTHxHEIGHT`` (a ``--resolution`` flag) as (width, height); None passes through."""
    if text is None:
        return None
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise InvalidInputError(f"--resolution must look like 640x480, got {text!r}") from None
    return w, h


def open_source(path: str | os.PathLike | None = None, *, live: bool = False, serial: str | None = None,
                pacing: Pacing | None = None, resolution: tuple[int, int] | None = None) -> EventSource:
    """``live=True``: the DAVIS on USB (``serial`` picks one). Otherwise a replay of ``path``, chosen
    by its suffix (.aedat4, .h5/.hdf5), played with ``pacing``; ``resolution`` (width, height) for HDF5
    layouts that do not store it.
    """
    if live:
        if path is not None:
            raise InvalidInputError("give either a recording path or live=True, not both")
        from edmcgs.sensor.sources.davis import DavisSource

        return DavisSource(serial)
    if path is None:
        raise InvalidInputError("a recording path is required unless live=True")
    suffix = Path(path).suffix.lower()
    if suffix in AEDAT_SUFFIXES:
        from edmcgs.sensor.sources.aedat import AedatReplay

        return AedatReplay(path, pacing)
    if suffix in HDF5_SUFFIXES:
        from edmcgs.sensor.sources.hdf5 import Hdf5Replay

        return Hdf5Replay(path, pacing, resolution=resolution)
    raise InvalidInputError(f"cannot replay {path}: expected a file ending in "
                            f"{', '.join(AEDAT_SUFFIXES + HDF5_SUFFIXES)}")
