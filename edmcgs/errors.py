"""The one error hierarchy of edmcgs.

Every error a user can act on is an ``EdmcgsError``; the server maps these classes to HTTP status
codes in one place (``edmcgs.server.errors``). Errors from dv-processing, pyusb, h5py and torch are
translated at the boundary with ``raise ... from exc`` so the cause stays visible (``translated``).
"""

from __future__ import annotations

import contextlib
import difflib
from collections.abc import Callable, Iterable, Iterator


class EdmcgsError(Exception):
    """Base class of every error edmcgs raises on purpose."""


class InvalidInputError(EdmcgsError, ValueError):
    """A public function got an argument it cannot use (wrong shape, dtype, NaN, out of range).

    The message names the argument and what was wrong with it.
    """


class PoseError(InvalidInputError):
    """A camera pose or quaternion is malformed: non-finite, not a rotation, zero quaternion."""


class PoseEstimationError(InvalidInputError):
    """A recording's camera poses cannot be estimated from its frames (too few register, none match)."""


class SensorError(EdmcgsError):
    """Something went wrong between an event camera (or recording) and the ring buffer."""


class DeviceNotFound(SensorError):
    """No event camera matching what was asked for is attached."""


class DeviceDisconnected(SensorError):
    """The camera went away mid-stream; what was buffered is kept and the caller may reconnect."""


class BackendMissing(SensorError):
    """A system library the sensor path needs (libusb) is not installed."""


class WindowUnavailable(SensorError):
    """An event window was asked for that the ring buffer no longer (or does not yet) retain."""


class ReplayFormatError(SensorError):
    """A recording file is of an unknown layout, truncated or corrupt."""


class RecordingError(EdmcgsError):
    """A recording could not be written."""


class CheckpointError(EdmcgsError):
    """A checkpoint is missing, truncated, foreign, or of a newer schema than this code reads."""


class RenderError(EdmcgsError):
    """A render failed for a reason other than its inputs."""


class DiskFullError(EdmcgsError):
    """A file could not be written because its file system is full (or the user's quota is); the file at
    the target path is left as it was (``edmcgs.atomic``)."""


class TrainingError(EdmcgsError):
    """Training cannot proceed (e.g. a recording without anchor frames)."""


def did_you_mean(name: str, known: Iterable[str]) -> str:
    """``"; did you mean 'x'?"`` naming the known names closest to a mistyped ``name``; '' when none is."""
    close = difflib.get_close_matches(name, list(known), n=3, cutoff=0.6)
    return f"; did you mean {' or '.join(repr(c) for c in close)}?" if close else ""


@contextlib.contextmanager
def translated(catch: tuple[type[BaseException], ...], into: Callable[[BaseException], BaseException], *,
               keep: tuple[type[BaseException], ...] = ()) -> Iterator[None]:
    """Re-raise an exception of a ``catch`` type raised in the block as ``into(exc)``, with ``exc`` as its
    cause; ``keep`` types (errors already said in our terms, which may be subclasses of a ``catch``
    type) pass through unchanged."""
    try:
        yield
    except keep:
        raise
    except catch as exc:
        raise into(exc) from exc
