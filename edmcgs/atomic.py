"""Atomic file output: write to a temporary file beside the target, fsync, then rename over it.

Every file the tools write (recordings, checkpoints, exports) goes through ``atomic_output``. An
interrupted write leaves at most a hidden ``.NAME.tmp-*`` file, never a file at the target path that
looks complete. The temporary name keeps the target's suffix, because some writers (dv-processing's
AEDAT4 writer) refuse any other. The writer creates the file itself, so it gets the usual permissions
(0666 less the umask), as any file the user's tools write.

A full disk is told here, once for every writer: whatever a writer raised when its file system filled
(torch's ``unexpected pos``, h5py's and dv-processing's own errors, a plain ``OSError``) becomes one
``DiskFullError`` naming the file. Libraries that write from C++ do not keep the errno, so after a
failed write the folder is probed with a write of our own (the temporary file is removed anyway).
"""

from __future__ import annotations

import contextlib
import errno
import os
import secrets
from collections.abc import Iterator
from pathlib import Path

from edmcgs.errors import DiskFullError, EdmcgsError

NO_SPACE = (errno.ENOSPC, errno.EDQUOT)
PROBE_BYTES = 1 << 16
"""What the probe of a folder whose write failed tries to write beside the failed file."""


def temp_path_for(path: Path) -> Path:
    """A fresh hidden temporary path in ``path``'s folder, with the same suffix."""
    return path.with_name(f".{path.stem}.tmp-{os.getpid()}-{secrets.token_hex(4)}{path.suffix}")


def _fsync(path: Path, *, directory: bool = False) -> None:
    fd = os.open(path, os.O_RDONLY | (os.O_DIRECTORY if directory else 0))
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def fsync_folder(folder: str | os.PathLike) -> None:
    """Make the renames in ``folder`` durable."""
    _fsync(Path(folder), directory=True)


@contextlib.contextmanager
def atomic_output(path: str | os.PathLike, error: type[EdmcgsError] = EdmcgsError) -> Iterator[Path]:
    """Yield a temporary path to write; on success it replaces ``path``, on error it is removed.

    The writer must have closed the temporary file when the block ends. Problems with the target
    (no such folder, a folder in the way, nothing written) raise ``error``; a full disk, whatever the
    writer raised, ``DiskFullError``.
    """
    path = Path(path)
    if not path.parent.is_dir():
        raise error(f"cannot write {path}: folder {path.parent} does not exist")
    if path.is_dir():
        raise error(f"cannot write {path}: it is a folder")
    tmp = temp_path_for(path)
    existed = path.exists()
    try:
        yield tmp
        if not tmp.exists():
            raise error(f"writing {path}: the writer produced no file")
        _fsync(tmp)
        os.replace(tmp, path)
        fsync_folder(path.parent)
    except BaseException as exc:
        full = isinstance(exc, Exception) and not isinstance(exc, DiskFullError) and _out_of_space(exc, tmp)
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()
        if full:
            raise _disk_full(path, existed) from exc
        raise


ROOM = 64 << 20
"""Free space a streaming writer keeps beyond twice what it is about to write (``ensure_room``)."""


def ensure_room(path: str | os.PathLike, size: int) -> None:
    """``DiskFullError`` unless ``path``'s folder has room for ``size`` more bytes and a margin, asked
    before each batch by the writers that cannot meet a full disk: dv-processing's AEDAT4 writer thread
    ends the whole process (std::terminate), and h5py's chunk cache drops its failed writes (printed as
    ignored, the file left corrupt) until the process segfaults. The margin leaves room for what they
    hold unwritten and for closing the file."""
    path = Path(path)
    stat = os.statvfs(path.parent)
    if stat.f_bavail * stat.f_frsize < ROOM + 2 * size:
        raise _disk_full(path, path.exists())


def _disk_full(path: Path, existed: bool) -> DiskFullError:
    kept = "left as it was" if existed else "not created"
    return DiskFullError(f"cannot write {path}: no space left on device ({path.name} {kept}; free some "
                         "space and run again)")


def _out_of_space(exc: BaseException, tmp: Path) -> bool:
    """Whether ``exc`` (or an error it came from) says the disk is full, or a write beside the failed
    file now fails so."""
    seen: set[int] = set()
    while exc is not None and id(exc) not in seen:
        seen.add(id(exc))
        if isinstance(exc, OSError) and exc.errno in NO_SPACE:
            return True
        exc = exc.__cause__ or exc.__context__
    try:
        fd = os.open(tmp, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o600)
    except OSError as probe:
        return probe.errno in NO_SPACE
    try:
        left, block = PROBE_BYTES, bytes(PROBE_BYTES)
        while left > 0:  # a nearly full disk takes part of a write; the next one then fails
            written = os.write(fd, block[:left])
            if written <= 0:
                break
            left -= written
    except OSError as probe:
        return probe.errno in NO_SPACE
    finally:
        os.close(fd)
    return False
