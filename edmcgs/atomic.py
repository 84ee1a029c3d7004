"""Atomic file output: write to a temporary file beside the target, fsync, then rename over it.

Every file the tools write (recordings, checkpoints, exports) goes through ``atomic_output``. An
interrupted write leaves at most a hidden ``.NAME.tmp-*`` file, never a file at the target path that
looks complete. The temporary name keeps the target's suffix, because some writers (dv-processing's
AEDAT4 writer) refuse any other. The writer creates the file itself, so it gets the usual permissions
(0666 less the umask), as any file the user's tools write.
"""

from __future__ import annotations

import contextlib
import os
import secrets
from collections.abc import Iterator
from pathlib import Path

from edmcgs.errors import EdmcgsError


def temp_path_for(path: Path) -> Path:
    """A fresh hidden temporary path in ``path``'s folder, with the same suffix."""
    return path.with_name(f".{path.stem}.tmp-{os.getpid()}-{secrets.token_hex(4)}{path.suffix}")


def _fsync(path: Path, *, directory: bool = False) -> None:
    fd = os.open(path, os.O_RDONLY | (os.O_DIRECTORY if directory else 0))
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


@contextlib.contextmanager
def atomic_output(path: str | os.PathLike, error: type[EdmcgsError] = EdmcgsError) -> Iterator[Path]:
    """Yield a temporary path to write; on success it replaces ``path``, on error it is removed.

    The writer must have closed the temporary file when the block ends. Problems with the target
    (no such folder, a folder in the way, nothing written) raise ``error``.
    """
    path = Path(path)
    if not path.parent.is_dir():
        raise error(f"cannot write {path}: folder {path.parent} does not exist")
    if path.is_dir():
        raise error(f"cannot write {path}: it is a folder")
    tmp = temp_path_for(path)
    try:
        yield tmp
        if not tmp.exists():
            raise error(f"writing {path}: the writer produced no file")
        _fsync(tmp)
        os.replace(tmp, path)
        _fsync(path.parent, directory=True)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()
        raise
