"""A batch of events: four equal-length columns, validated at the boundary.

Columns (numpy, 1-D, equal length N):

- ``t``: int64 microseconds, non-decreasing (Unix-epoch or synthetic time; never float: ~1.6e15 µs
  does not fit float32 and float64 hides unit mistakes).
- ``x``, ``y``: uint16 pixel coordinates.
- ``p``: int8 polarity, +1 (ON, brighter) or -1 (OFF).

Two ways in:

- ``Events(t, x, y, p)`` is strict: it converts value-preserving dtypes and raises
  ``InvalidInputError`` on anything else (polarity not ±1, time going backwards, ...).
- ``Events.from_arrays(t, x, y, p, width=, height=)`` is for raw sensor or file data: it normalises
  polarity from {0, 1}, bool or {-1, +1}, drops (and counts) coordinates outside the resolution, sorts
  events that are out of order by at most ``max_disorder_us`` and drops (and counts) those further
  behind. It returns the events and an ``EventStats`` saying what happened: nothing is lost silently.
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence
from dataclasses import dataclass, fields

import numpy as np

from edmcgs.errors import InvalidInputError

# Events may arrive up to this much earlier than an event before them and are sorted into place;
# further behind, they are dropped and counted. 1 ms covers USB packet reordering and the small
# non-monotonic runs some simulators (v2e) write, without hiding a clock that jumped back.
DEFAULT_MAX_DISORDER_US = 1_000

_INT64_MAX = np.iinfo(np.int64).max


@dataclass
class EventStats:
    """What validation did to a stream of raw events (counts accumulate over batches)."""

    received: int = 0
    """Raw events seen."""
    kept: int = 0
    """Events that passed and were returned."""
    out_of_bounds: int = 0
    """Dropped: x or y outside the sensor resolution (or negative)."""
    backwards: int = 0
    """Dropped: earlier than an event before them by more than ``max_disorder_us``."""
    late: int = 0
    """Dropped: earlier than ``not_before_us`` (a batch already emitted covered that time)."""
    reordered: int = 0
    """Kept, but out of order within the tolerance and sorted into place."""

    @property
    def dropped(self) -> int:
        return self.out_of_bounds + self.backwards + self.late

    def add(self, other: EventStats) -> None:
        """Accumulate ``other`` into this one, in place."""
        for f in fields(self):
            setattr(self, f.name, getattr(self, f.name) + getattr(other, f.name))

    def as_dict(self) -> dict[str, int]:
        return {f.name: getattr(self, f.name) for f in fields(self)} | {"dropped": self.dropped}


def _column(name: str, values) -> np.ndarray:
    arr = np.asarray(values)
    if arr.size == 0 and arr.dtype == np.float64:  # np.asarray([]) is float64: an empty list has no dtype
        arr = arr.astype(np.int64)
    if arr.ndim != 1:
        raise InvalidInputError(f"events column {name!r} must be 1-D, got shape {arr.shape}")
    return arr


def _integer_column(name: str, arr: np.ndarray, dtype, lo: int, hi: int) -> np.ndarray:
    """Convert an integer column to ``dtype`` if every value fits in [lo, hi]; else raise."""
    if arr.dtype == dtype:
        return arr
    if arr.dtype.kind not in "iub":
        raise InvalidInputError(f"events column {name!r} must be integer, got dtype {arr.dtype}")
    if arr.size and (int(arr.min()) < lo or int(arr.max()) > hi):
        bad = arr[(arr < lo) | (arr > hi)][0]
        raise InvalidInputError(
            f"events column {name!r} has value {bad} outside [{lo}, {hi}] for dtype {np.dtype(dtype)}")
    return arr.astype(dtype)


def _time_column(arr: np.ndarray) -> np.ndarray:
    if arr.dtype.kind == "f":
        raise InvalidInputError(
            f"events column 't' must be integer microseconds, got dtype {arr.dtype} "
            "(convert seconds with np.round(t_s * 1e6).astype(np.int64))")
    return _integer_column("t", arr, np.int64, -_INT64_MAX - 1, _INT64_MAX)


def normalize_polarity(p) -> np.ndarray:
    """Polarity as int8 ±1 from bool, {0, 1} (0 = OFF) or {-1, +1}. Anything else raises.

    An array holding only 1s reads the same under both conventions. A mix of -1, 0 and 1 is
    ambiguous and rejected.
    """
    p = _column("p", p)
    if p.dtype == np.bool_:
        return np.where(p, np.int8(1), np.int8(-1))
    if p.dtype.kind not in "iuf":
        raise InvalidInputError(f"events column 'p' must be bool or numeric, got dtype {p.dtype}")
    if p.size == 0:
        return np.empty(0, np.int8)
    if p.dtype.kind == "f":
        finite_int = np.isfinite(p) & (p == np.round(p))
        if not finite_int.all():
            raise InvalidInputError(f"events column 'p' has non-integer value {p[~finite_int][0]}")
    lo, hi = p.min(), p.max()
    if lo >= 0 and hi <= 1:  # {0, 1}: 0 is OFF
        return (p.astype(np.int8) << 1) - np.int8(1)
    if lo >= -1 and hi <= 1:
        if np.any(p == 0):
            raise InvalidInputError(
                "events column 'p' mixes -1, 0 and 1; expected one convention: {0, 1}, {-1, +1} or bool")
        return p.astype(np.int8)
    bad = p[(p < -1) | (p > 1)][0]
    raise InvalidInputError(f"events column 'p' has value {bad}; expected {{0, 1}}, {{-1, +1}} or bool")


class Events:
    """A batch of events (see the module docstring). Slicing returns views, never copies."""

    __slots__ = ("p", "t", "x", "y")
    __hash__ = None  # mutable arrays inside

    t: np.ndarray  # [N] int64 µs, non-decreasing
    x: np.ndarray  # [N] uint16
    y: np.ndarray  # [N] uint16
    p: np.ndarray  # [N] int8, ±1

    def __init__(self, t, x, y, p) -> None:
        t, x, y, p = (_column(n, v) for n, v in zip("txyp", (t, x, y, p), strict=True))
        if not len(t) == len(x) == len(y) == len(p):
            raise InvalidInputError(
                f"events columns must have equal length, got t={len(t)} x={len(x)} y={len(y)} p={len(p)}")
        t = _time_column(t)
        x = _integer_column("x", x, np.uint16, 0, 65535)
        y = _integer_column("y", y, np.uint16, 0, 65535)
        p = _integer_column("p", p, np.int8, -128, 127)
        if p.size and not np.all((p == 1) | (p == -1)):
            raise InvalidInputError(
                f"events column 'p' must be +1 or -1, found {p[(p != 1) & (p != -1)][0]} "
                "(use Events.from_arrays to normalise {0, 1} or bool polarity)")
        if t.size > 1 and np.any(t[1:] < t[:-1]):
            i = int(np.argmax(t[1:] < t[:-1]))
            raise InvalidInputError(
                f"events column 't' goes backwards at index {i + 1} ({t[i]} -> {t[i + 1]} µs); "
                "use Events.from_arrays to sort or drop out-of-order events")
        self._set(t, x, y, p)

    def _set(self, t, x, y, p) -> None:
        object.__setattr__(self, "t", t)
        object.__setattr__(self, "x", x)
        object.__setattr__(self, "y", y)
        object.__setattr__(self, "p", p)

    @classmethod
    def _trusted(cls, t: np.ndarray, x: np.ndarray, y: np.ndarray, p: np.ndarray) -> Events:
        """Wrap columns already known to satisfy the contract (internal hot paths only)."""
        ev = object.__new__(cls)
        ev._set(t, x, y, p)
        return ev

    @classmethod
    def empty(cls) -> Events:
        return cls._trusted(np.empty(0, np.int64), np.empty(0, np.uint16), np.empty(0, np.uint16),
                            np.empty(0, np.int8))

    @classmethod
    def from_arrays(cls, t, x, y, p, *, width: int, height: int,
                    max_disorder_us: int = DEFAULT_MAX_DISORDER_US,
                    not_before_us: int | None = None) -> tuple[Events, EventStats]:
        """Validate raw columns from a sensor or a file; see the module docstring.

        t: [N] integer µs; x, y: [N] integers (any signed/unsigned dtype; out-of-range ones are
        dropped); p: [N] bool, {0, 1} or {-1, +1}. ``not_before_us``: events earlier than this are
        dropped as ``late`` (a previous batch already covered that time).
        Returns (events sorted by t, counts).
        """
        if int(width) <= 0 or int(height) <= 0:
            raise InvalidInputError(f"resolution must be positive, got width={width} height={height}")
        if max_disorder_us < 0:
            raise InvalidInputError(f"max_disorder_us must be >= 0, got {max_disorder_us}")
        t, x, y = _column("t", t), _column("x", x), _column("y", y)
        p = normalize_polarity(p)
        if not len(t) == len(x) == len(y) == len(p):
            raise InvalidInputError(
                f"events columns must have equal length, got t={len(t)} x={len(x)} y={len(y)} p={len(p)}")
        t = _time_column(t)
        for name, c in (("x", x), ("y", y)):
            if c.dtype.kind not in "iu":
                raise InvalidInputError(f"events column {name!r} must be integer, got dtype {c.dtype}")
        stats = EventStats(received=len(t))

        keep = (x < width) & (y < height)
        if x.dtype.kind == "i":
            keep &= x >= 0
        if y.dtype.kind == "i":
            keep &= y >= 0
        stats.out_of_bounds = int(len(keep) - np.count_nonzero(keep))
        if not_before_us is not None:
            on_time = t >= not_before_us
            stats.late = int(np.count_nonzero(keep & ~on_time))
            keep &= on_time
        if not keep.all():
            t, x, y, p = t[keep], x[keep], y[keep], p[keep]

        if t.size > 1 and np.any(t[1:] < t[:-1]):
            behind = np.maximum.accumulate(t) - t
            ok = behind <= max_disorder_us
            stats.backwards = int(len(ok) - np.count_nonzero(ok))
            if stats.backwards:
                t, x, y, p, behind = t[ok], x[ok], y[ok], p[ok], behind[ok]
            stats.reordered = int(np.count_nonzero(behind))
            order = np.argsort(t, kind="stable")
            t, x, y, p = t[order], x[order], y[order], p[order]
        stats.kept = len(t)
        return cls._trusted(t, x.astype(np.uint16, copy=False), y.astype(np.uint16, copy=False), p), stats

    @classmethod
    def concat(cls, parts: Sequence[Events]) -> Events:
        """Join batches in order. Raises if time would go backwards across a seam."""
        parts = [e for e in parts if len(e)]
        if not parts:
            return cls.empty()
        if len(parts) == 1:
            return parts[0]
        for a, b in itertools.pairwise(parts):
            if b.t[0] < a.t[-1]:
                raise InvalidInputError(
                    f"cannot concatenate events: a batch starts at {b.t[0]} µs, before the previous "
                    f"batch ends ({a.t[-1]} µs)")
        return cls._trusted(*(np.concatenate([getattr(e, c) for e in parts]) for c in "txyp"))

    def __len__(self) -> int:
        return len(self.t)

    def __getitem__(self, key) -> Events:
        if isinstance(key, slice):
            if key.step not in (None, 1):
                raise InvalidInputError("events can only be sliced with step 1 (time order)")
            return Events._trusted(self.t[key], self.x[key], self.y[key], self.p[key])
        key = np.asarray(key)
        if key.dtype == np.bool_:
            if key.shape != self.t.shape:
                raise InvalidInputError(f"boolean mask must have shape {self.t.shape}, got {key.shape}")
            return Events._trusted(self.t[key], self.x[key], self.y[key], self.p[key])
        raise InvalidInputError("events are indexed by a slice or a boolean mask (to keep time order)")

    def time_slice(self, t0_us: int, t1_us: int) -> Events:
        """Events with t0_us <= t < t1_us (views), found by binary search."""
        i0, i1 = np.searchsorted(self.t, [t0_us, t1_us], side="left")
        return self[int(i0):int(i1)]

    def shifted(self, dt_us: int) -> Events:
        """The same events ``dt_us`` later (a copy of t; x, y, p shared)."""
        return Events._trusted(self.t + np.int64(dt_us), self.x, self.y, self.p)

    @property
    def t_start(self) -> int | None:
        return int(self.t[0]) if len(self.t) else None

    @property
    def t_end(self) -> int | None:
        """Time of the last event (inclusive), or None when empty."""
        return int(self.t[-1]) if len(self.t) else None

    @property
    def nbytes(self) -> int:
        return self.t.nbytes + self.x.nbytes + self.y.nbytes + self.p.nbytes

    def copy(self) -> Events:
        return Events._trusted(self.t.copy(), self.x.copy(), self.y.copy(), self.p.copy())

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, Events):
            return NotImplemented
        return all(np.array_equal(getattr(self, c), getattr(other, c)) for c in "txyp")

    def __repr__(self) -> str:
        if not len(self):
            return "Events(n=0)"
        return f"Events(n={len(self)}, t=[{self.t[0]}, {self.t[-1]}] µs, on={int(np.sum(self.p > 0))})"
