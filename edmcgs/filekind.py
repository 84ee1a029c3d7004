"""What a file is, told by its first bytes with nothing heavy imported (no torch, numba or h5py).

The commands check the files they are given with it before they load torch or a model, so a wrong file is
one line within a second, and a recording given where a checkpoint belongs (or the reverse) is named as
such. Recordings: HDF5 (its signature at offset 0, or after a user block at 512, 1024, 2048 ...) and
AEDAT4 (a ``#!AER-DAT4.0`` header). Checkpoints are torch files: a zip archive holding ``.../data.pkl``.
"""

from __future__ import annotations

import os
import zipfile
import zlib
from pathlib import Path

from edmcgs.errors import CheckpointError, InvalidInputError

AEDAT_SUFFIXES = (".aedat4",)
HDF5_SUFFIXES = (".h5", ".hdf5")
HDF5_SIGNATURE = b"\x89HDF\r\n\x1a\n"
AEDAT4_HEADER = b"#!AER-DAT4.0"
_MAGIC = ((HDF5_SIGNATURE, "hdf5"), (AEDAT4_HEADER, "aedat4"), (b"PK\x03\x04", "zip"),
          (b"\x89PNG\r\n\x1a\n", "png"), (b"\xff\xd8\xff", "jpeg"))
NAMES = {"hdf5": "an HDF5 recording", "aedat4": "an AEDAT4 recording",
         "checkpoint": "a checkpoint (a torch file)", "zip": "a zip archive, not a torch file",
         "png": "a PNG image", "jpeg": "a JPEG image", "empty": "an empty file"}
"""How a message names each kind ``sniff`` tells."""
RECORDINGS = "AEDAT4 (.aedat4) or HDF5 (.h5, .hdf5)"


def sniff(path: str | os.PathLike) -> str | None:
    """The kind of the file at ``path`` (a key of ``NAMES``), or None when its first bytes are none of
    them. A zip archive is a ``checkpoint`` when it holds a torch pickle, else ``zip`` (unreadable ones
    too). OSError when it cannot be read."""
    with open(path, "rb") as f:
        head = f.read(16)
        if not head:
            return "empty"
        kind = next((k for magic, k in _MAGIC if head.startswith(magic)), None)
        if kind is None:
            kind = _hdf5_after_user_block(f)
        if kind != "zip":
            return kind
    try:
        with zipfile.ZipFile(path) as archive:
            return "checkpoint" if _torch_pickle(archive) else "zip"
    except (zipfile.BadZipFile, OSError, ValueError):
        return "zip"


def _hdf5_after_user_block(f) -> str | None:
    size = os.fstat(f.fileno()).st_size
    offset = 512
    while offset + len(HDF5_SIGNATURE) <= size:
        f.seek(offset)
        if f.read(len(HDF5_SIGNATURE)) == HDF5_SIGNATURE:
            return "hdf5"
        offset *= 2
    return None


def _torch_pickle(archive: zipfile.ZipFile) -> bool:
    return any(name == "data.pkl" or name.endswith("/data.pkl") for name in archive.namelist())


def check_recording(path: str | os.PathLike, *, hint: str = "") -> Path:
    """``path`` if it is an HDF5 or AEDAT4 recording named by its format's suffix, else InvalidInputError in
    one line naming what it is; ``hint`` is said after a checkpoint given in a recording's place."""
    path = Path(path)
    if not path.is_file():
        raise InvalidInputError(f"{path}: no such file" + (" (a folder)" if path.is_dir() else ""))
    kind = _kind(path, InvalidInputError)
    if kind == "checkpoint":
        raise InvalidInputError(f"{path} is {NAMES[kind]}, not a recording" + (f": {hint}" if hint else ""))
    if kind not in ("hdf5", "aedat4"):
        what = NAMES.get(kind, "neither HDF5 nor AEDAT4 by its first bytes")
        raise InvalidInputError(f"{path} is not a recording ({what}); expected {RECORDINGS}")
    suffixes = HDF5_SUFFIXES if kind == "hdf5" else AEDAT_SUFFIXES
    if path.suffix.lower() not in suffixes:
        named = f"named {path.suffix!r}" if path.suffix else "named without a suffix"
        raise InvalidInputError(f"{path} is {NAMES[kind]} but {named}; rename it to end in {suffixes[0]}")
    return path


def check_checkpoint(path: str | os.PathLike, *, hint: str = "", verify: bool = False) -> Path:
    """``path`` if it is a readable torch file, else CheckpointError in one line naming what it is (a
    recording: followed by ``hint``). verify: also read every member against its CRC (a partial copy, a
    flipped bit), at disk speed."""
    path = Path(path)
    if not path.is_file():
        folder = " (a folder)" if path.is_dir() else ""
        raise CheckpointError(f"checkpoint {str(path)!r} does not exist{folder}")
    kind = _kind(path, CheckpointError)
    if kind in ("hdf5", "aedat4"):
        raise CheckpointError(f"{path} is {NAMES[kind]}, not a checkpoint" + (f": {hint}" if hint else ""))
    if kind not in ("checkpoint", "zip"):
        what = NAMES.get(kind, "not a torch file by its first bytes")
        raise CheckpointError(f"{path} is not a checkpoint ({what}); give one written by edmcgs train")
    try:
        with zipfile.ZipFile(path) as archive:
            if not _torch_pickle(archive):
                raise CheckpointError(f"{path} is not a checkpoint ({NAMES['zip']})")
            damaged = archive.testzip() if verify else None
    except (zipfile.BadZipFile, OSError, ValueError, EOFError, zlib.error) as exc:
        raise CheckpointError(f"checkpoint {str(path)!r} is truncated or not a torch file: {exc}") from None
    if damaged is not None:
        raise CheckpointError(f"checkpoint {str(path)!r} is damaged: its part {damaged} does not match its "
                              "CRC (a partial copy, a flipped bit); use another copy")
    return path


def _kind(path: Path, error: type[Exception]) -> str | None:
    try:
        return sniff(path)
    except OSError as exc:
        raise error(f"{path}: cannot read it: {exc.strerror or exc}") from None
