"""A recording's events left in its file, read a time window at a time: a recording of any length.

``FileEvents`` is an index range [i0, i1) of an open ``RecordingFile``'s event columns, with what a
``Recording`` asks of its events (``len``, ``t_start``, ``t_end``, ``time_slice``, index slices) and
``read(t0, t1)``: the events of [t0, t1) as ``Events``. A time is found through a coarse index (the
time of every ``STRIDE``-th event, read once in one chunked pass: 2 kB per million events), then one
short slice of the time column. A read takes a block of at least ``BLOCK_EVENTS`` events from where it
starts and keeps it, so the consecutive windows of a gap (training's sub-steps, evaluation's frames in
time order) cost one read of the file: memory holds one block, never the recording.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from edmcgs.errors import InvalidInputError
from edmcgs.sensor.events import Events

STRIDE = 4096
"""Events between two entries of the coarse time index."""
BLOCK_EVENTS = 1 << 18
"""Events a read takes at least (3.4 MB; 0.6 s of a DAVIS346 street at 0.42 M events/s)."""


class _TimeIndex:
    """The time of every ``STRIDE``-th event of a file and a lookup of any time's first event."""

    def __init__(self, source) -> None:
        self.source = source
        self.n = source.n_events
        step = STRIDE * 64  # a multiple of STRIDE: each part's every STRIDE-th event continues the last
        self.coarse = np.concatenate([np.zeros(0, np.int64)] + [
            source.read_times(i, min(i + step, self.n), STRIDE) for i in range(0, self.n, step)])

    def first_at_or_after(self, t_us: int) -> int:
        """The index of the first event with time >= ``t_us`` (``n`` when none)."""
        j = int(np.searchsorted(self.coarse, t_us, side="left"))
        if j == 0:
            return 0
        lo = (j - 1) * STRIDE
        times = self.source.read_times(lo, min(j * STRIDE, self.n))
        return lo + int(np.searchsorted(times, t_us, side="left"))


@dataclass
class _Block:
    """Events [start, start + len(events)) of the file, and the times just outside them."""

    start: int
    events: Events
    before_us: int | None
    """Time of event start - 1 (None at the file's start)."""
    after_us: int | None
    """Time of the event after the block (None at the file's end)."""

    def covers(self, t_us: int) -> bool:
        """Whether the first event at or after ``t_us`` is known from this block alone."""
        return (self.before_us is None or t_us > self.before_us) and (self.after_us is None
                                                                        or t_us <= self.after_us)

    def first_at_or_after(self, t_us: int) -> int:
        return self.start + int(np.searchsorted(self.events.t, t_us, side="left"))


class _Reader:
    """What the views of one file share: the file, its time index (built on first use), the last block."""

    def __init__(self, source) -> None:
        self.source = source
        self._index: _TimeIndex | None = None
        self.block: _Block | None = None

    @property
    def index(self) -> _TimeIndex:
        if self._index is None:
            self._index = _TimeIndex(self.source)
        return self._index

    def first_at_or_after(self, t_us: int) -> int:
        block = self.block
        if block is not None and block.covers(t_us):
            return block.first_at_or_after(t_us)
        return self.index.first_at_or_after(t_us)

    def events(self, i0: int, i1: int) -> Events:
        """Events [i0, i1), from the last block when it holds them, else in a new block from i0."""
        block = self.block
        if block is None or not (block.start <= i0 and i1 <= block.start + len(block.events)):
            n = self.source.n_events
            end = min(max(i1, i0 + BLOCK_EVENTS), n)
            first, last = max(i0 - 1, 0), min(end + 1, n)  # and the events either side: their times
            read = self.source.read_events(first, last)
            before = int(read.t[0]) if i0 > 0 else None
            after = int(read.t[-1]) if end < n else None
            self.block = block = _Block(i0, read[i0 - first:end - first], before, after)
        return block.events[i0 - block.start:i1 - block.start]


class FileEvents:
    """The events [i0, i1) of an open ``RecordingFile`` (see the module docstring); views share one
    reader, and keep the file open."""

    __hash__ = None

    def __init__(self, source, i0: int = 0, i1: int | None = None, *, _reader: _Reader | None = None) -> None:
        self._reader = _Reader(source) if _reader is None else _reader
        self.source = source
        self.i0 = int(i0)
        self.i1 = source.n_events if i1 is None else int(i1)
        if not 0 <= self.i0 <= self.i1 <= source.n_events:
            raise InvalidInputError(f"event range [{i0}, {i1}) outside the file's {source.n_events} events")

    def __len__(self) -> int:
        return self.i1 - self.i0

    def __repr__(self) -> str:
        return f"FileEvents({self.source.path}, [{self.i0}, {self.i1}))"

    @property
    def t_start(self) -> int | None:
        """Time of the first event (None when empty)."""
        return int(self.source.read_times(self.i0, self.i0 + 1)[0]) if len(self) else None

    @property
    def t_end(self) -> int | None:
        """Time of the last event (None when empty)."""
        return int(self.source.read_times(self.i1 - 1, self.i1)[0]) if len(self) else None

    def _index(self, t_us: int, lowest: int) -> int:
        """The first event of the view at or after ``t_us``, no earlier than ``lowest``."""
        return min(max(self._reader.first_at_or_after(int(t_us)), lowest), self.i1)

    def time_slice(self, t0_us: int, t1_us: int) -> FileEvents:
        """The events with t0 <= t < t1, left in the file (a view)."""
        i = self._index(t0_us, self.i0)
        return FileEvents(self.source, i, self._index(t1_us, i), _reader=self._reader)

    def read(self, t0_us: int | None = None, t1_us: int | None = None) -> Events:
        """The events with t0 <= t < t1 (None: from the view's first, to its last), read from the file."""
        i = self.i0 if t0_us is None else self._index(t0_us, self.i0)
        k = self.i1 if t1_us is None else self._index(t1_us, i)
        return self._reader.events(i, k)

    def __getitem__(self, item: slice) -> Events:
        """Events by position within the view (a slice with step 1), read from the file."""
        if not isinstance(item, slice) or item.step not in (None, 1):
            raise InvalidInputError("FileEvents takes a slice of positions")
        start, stop, _ = item.indices(len(self))
        return self.source.read_events(self.i0 + start, self.i0 + max(start, stop))
