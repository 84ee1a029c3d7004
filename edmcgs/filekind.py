"""What a file is, told by its first bytes with nothing heavy imported (no torch, numba or h5py): the one
place that knows each format's signature.

The commands check the files they are given with it before they load torch or a model, so a wrong file is
one line within a second, and a recording given where a checkpoint belongs (or the reverse) is named as
such; the sensor layer picks a recording's reader by it (``sensor/sources/open.py``). Recordings: AEDAT4
(``#!AER-DAT4``), AEDAT 2.0 / 3.1 (jAER), Prophesee RAW (a ``% `` header) and DAT, HDF5 (its signature at
offset 0, or after a user block at 512, 1024, 2048 ...), ROS 1 and 2 bags, and the RPG text layout (a
folder with ``events.txt``, or that file). Checkpoints are torch files: a zip archive holding
``.../data.pkl``.
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
_MAGIC = ((b"#!AER-DAT4", "aedat4"), (b"#!AER-DAT2", "jaer"), (b"#!AER-DAT3", "jaer"),
          (HDF5_SIGNATURE, "hdf5"), (b"#ROSBAG V2.0", "rosbag"), (b"\x89MCAP", "rosbag"),
          (b"SQLite format 3\x00", "rosbag"), (b"% ", "prophesee"), (b"PK\x03\x04", "zip"),
          (b"\x89PNG\r\n\x1a\n", "png"), (b"\xff\xd8\xff", "jpeg"))
RECORDING_KINDS = ("aedat4", "jaer", "prophesee", "hdf5", "rosbag", "rpg")
"""The kinds ``sniff`` tells that are recordings (each the name of its reader in ``sensor/sources``)."""
NAMES = {"aedat4": "an AEDAT4 recording", "jaer": "an AEDAT 2.0 / 3.1 recording",
         "prophesee": "a Prophesee RAW / DAT recording", "hdf5": "an HDF5 recording",
         "rosbag": "a ROS bag", "rpg": "an RPG-layout recording", "checkpoint": "a checkpoint (a torch file)",
         "zip": "a zip archive, not a torch file", "png": "a PNG image", "jpeg": "a JPEG image",
         "empty": "an empty file", "folder": "a folder"}
"""How a message names each kind ``sniff`` tells."""
FORMATS = (
    "AEDAT4 (iniVation DV)",
    "AEDAT 2.0 / 3.1 (jAER, cAER)",
    "Prophesee RAW (EVT 2.0, 2.1, 3.0) and DAT",
    "HDF5 (edmcgs recording, DSEC, v2e)",
    "ROS 1 bag and ROS 2 bag (a folder with metadata.yaml, or its .db3 / .mcap)",
    "the RPG text layout (a folder with events.txt [images.txt, imu.txt, groundtruth.txt, calib.txt])",
)
"""The recordings read here, for messages."""
RECORDINGS = "; ".join(FORMATS)


def sniff(path: str | os.PathLike) -> str | None:
    """The kind of the file (or folder) at ``path`` (a key of ``NAMES``), or None when its first bytes are
    none of them. A zip archive is a ``checkpoint`` when it holds a torch pickle, else ``zip`` (unreadable
    ones too). OSError when it cannot be read."""
    path = Path(path)
    if path.is_dir():
        if (path / "events.txt").is_file():
            return "rpg"
        return "rosbag" if (path / "metadata.yaml").is_file() else "folder"
    if path.name == "events.txt":
        return "rpg"
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


def recording_kind(path: str | os.PathLike, *, hint: str = "", error: type[Exception] = InvalidInputError
                   ) -> str:
    """The kind of recording at ``path`` (``RECORDING_KINDS``), else ``error`` in one line naming what it
    is; ``hint`` is said after a checkpoint given in a recording's place."""
    path = Path(path)
    if not path.exists():
        raise error(f"{path}: no such file")
    kind = _kind(path, error)
    if kind == "checkpoint":
        raise error(f"{path} is {NAMES[kind]}, not a recording" + (f": {hint}" if hint else ""))
    if kind not in RECORDING_KINDS:
        what = NAMES.get(kind, f"it starts with {_head(path)!r}")
        raise error(f"{path} is not a recording read here ({what}); recordings read here: {RECORDINGS}")
    return kind


def check_recording(path: str | os.PathLike, *, hint: str = "") -> Path:
    """``path`` if it is a recording in a format read here (by its content), else InvalidInputError in one
    line naming what it is (``recording_kind``)."""
    recording_kind(path, hint=hint)
    return Path(path)


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


def _head(path: Path) -> bytes:
    with open(path, "rb") as f:
        return f.read(16)


def _kind(path: Path, error: type[Exception]) -> str | None:
    try:
        return sniff(path)
    except OSError as exc:
        raise error(f"{path}: cannot read it: {exc.strerror or exc}") from None
