"""The event ring buffer: the last N events, one writer thread, many readers, time windows by binary search.

Storage is four preallocated columns of ``capacity`` events (13 bytes each); memory never grows.
Events are kept in time order (a ring of a sorted sequence is two sorted runs), so a window
[t0, t1) is found by two binary searches and copied out under a lock: readers get a consistent copy
while the writer keeps appending.

Nothing is cut silently:

- On overflow the oldest events are dropped and counted (``overflowed``); with ``retention_us``,
  events older than that behind the newest are dropped too (``expired``).
- A window reaching back to time that was dropped raises ``WindowUnavailable`` saying what is
  retained; so does a window reaching past the *watermark*, the time below which the stream is
  known complete (events at the newest timestamp may still be arriving; a source can advance it
  further with ``complete_until_us``).
- Events pushed behind the watermark are dropped and counted (``late``).
"""

from __future__ import annotations

import threading
from dataclasses import asdict, dataclass

import numpy as np

from edmcgs.errors import InvalidInputError, WindowUnavailable
from edmcgs.sensor.events import Events

BYTES_PER_EVENT = 8 + 2 + 2 + 1


@dataclass(frozen=True)
class RingStats:
    """A consistent snapshot of the ring, for metrics."""

    capacity: int
    """Events the ring can hold."""
    size: int
    """Events held now."""
    fill: float
    """size / capacity."""
    head_us: int | None
    """Time of the newest event."""
    oldest_us: int | None
    """Time of the oldest event held."""
    watermark_us: int | None
    """Every event with t < watermark_us has been received."""
    pushed: int
    """Events ever offered to push()."""
    overflowed: int
    """Dropped to make room (oldest first)."""
    expired: int
    """Dropped for being older than retention_us behind the newest."""
    late: int
    """Dropped on push for arriving behind the watermark."""
    nbytes: int
    """Memory held by the columns."""

    def as_dict(self) -> dict:
        return asdict(self)


class EventRingBuffer:
    """``capacity``: events held at most (memory = 13 bytes x capacity, allocated up front).
    ``retention_us``: optionally, also drop events older than this behind the newest event.
    """

    def __init__(self, capacity: int, *, retention_us: int | None = None) -> None:
        if isinstance(capacity, bool) or int(capacity) != capacity or capacity <= 0:
            raise InvalidInputError(f"capacity must be a positive integer number of events, got {capacity!r}")
        if retention_us is not None and retention_us <= 0:
            raise InvalidInputError(f"retention_us must be positive, got {retention_us}")
        self.capacity = int(capacity)
        self.retention_us = None if retention_us is None else int(retention_us)
        self._t = np.empty(self.capacity, np.int64)
        self._x = np.empty(self.capacity, np.uint16)
        self._y = np.empty(self.capacity, np.uint16)
        self._p = np.empty(self.capacity, np.int8)
        for a in (self._t, self._x, self._y, self._p):
            a.fill(0)  # touch every page now: the memory bound is paid up front, not during a stream
        self._lock = threading.Lock()
        # Logical indices count every event ever stored; event i lives at slot i % capacity.
        self._start = 0  # oldest retained
        self._end = 0  # one past the newest
        self._dropped_max_t: int | None = None  # newest time no longer retained
        self._watermark: int | None = None
        self._pushed = self._overflowed = self._expired = self._late = 0

    # ------------------------------------------------------------------ writer

    def push(self, events: Events, *, complete_until_us: int | None = None) -> int:
        """Append a batch (sorted, as every ``Events`` is). Returns how many were stored.

        ``complete_until_us``: the source vouches that every event with t < this has now been pushed
        (e.g. the end of a replay batch window), so windows up to it can be served.
        """
        if not isinstance(events, Events):
            raise InvalidInputError(f"events must be an Events batch, got {type(events).__name__}")
        with self._lock:
            self._pushed += len(events)
            if self._watermark is not None and len(events) and events.t[0] < self._watermark:
                keep = int(np.searchsorted(events.t, self._watermark, side="left"))
                self._late += keep
                events = events[keep:]
            n = len(events)
            if n:
                self._write(events)
                self._advance_watermark(events.t_end)
            if complete_until_us is not None:
                self._advance_watermark(int(complete_until_us))
            if self.retention_us is not None and self._end > self._start:
                self._expire(int(self._t[(self._end - 1) % self.capacity]) - self.retention_us)
            return n

    def _write(self, events: Events) -> None:
        cap, n = self.capacity, len(events)
        if n > cap:  # only the newest `cap` can be kept
            self._overflowed += n - cap
            self._note_dropped(int(events.t[n - cap - 1]))
            events = events[n - cap:]
            n = cap
        new_end = self._end + n
        new_start = max(self._start, new_end - cap)
        if new_start > self._start:  # about to overwrite the oldest: remember the newest time lost
            self._overflowed += new_start - self._start
            self._note_dropped(int(self._t[(new_start - 1) % cap]))
            self._start = new_start
        s = self._end % cap
        first = min(n, cap - s)
        for dst, src in ((self._t, events.t), (self._x, events.x), (self._y, events.y), (self._p, events.p)):
            dst[s:s + first] = src[:first]
            dst[:n - first] = src[first:]
        self._end = new_end

    def _note_dropped(self, t_us: int) -> None:
        self._dropped_max_t = t_us if self._dropped_max_t is None else max(self._dropped_max_t, t_us)

    def _expire(self, older_than_us: int) -> None:
        i = self._search(older_than_us)
        if i > self._start:
            self._expired += i - self._start
            self._note_dropped(int(self._t[(i - 1) % self.capacity]))
            self._start = i

    def mark_complete(self, until_us: int) -> None:
        """Declare every event with t < until_us received (e.g. a replay reached its end)."""
        with self._lock:
            self._advance_watermark(int(until_us))

    def _advance_watermark(self, t_us: int) -> None:
        self._watermark = t_us if self._watermark is None else max(self._watermark, t_us)

    # ------------------------------------------------------------------ readers

    def _search(self, t_us: int) -> int:
        """Logical index of the first retained event with t >= t_us (lock held)."""
        cap, start, end = self.capacity, self._start, self._end
        s = start % cap
        n = end - start
        if s + n <= cap:
            return start + int(np.searchsorted(self._t[s:s + n], t_us, side="left"))
        first = self._t[s:]  # logical [start, start + len(first)), then the wrapped run [0, n - len(first))
        if len(first) and first[-1] >= t_us:
            return start + int(np.searchsorted(first, t_us, side="left"))
        return start + len(first) + int(np.searchsorted(self._t[:n - len(first)], t_us, side="left"))

    def _copy(self, i0: int, i1: int) -> Events:
        cap, n = self.capacity, i1 - i0
        s = i0 % cap
        if s + n <= cap:
            cols = [a[s:s + n].copy() for a in (self._t, self._x, self._y, self._p)]
        else:
            k = cap - s
            cols = [np.concatenate((a[s:], a[:n - k])) for a in (self._t, self._x, self._y, self._p)]
        return Events._trusted(*cols)

    def _check_window(self, t0_us: int, t1_us: int) -> None:
        if self._dropped_max_t is not None and t0_us <= self._dropped_max_t:
            oldest = int(self._t[self._start % self.capacity]) if self._end > self._start else None
            raise WindowUnavailable(
                f"events from {t0_us} µs are no longer retained: the ring keeps the newest {self.capacity} "
                f"events" + (f" and {self.retention_us} µs" if self.retention_us else "")
                + f"; it now holds t >= {oldest} µs (complete for t > {self._dropped_max_t} µs)")
        if self._watermark is None:
            raise WindowUnavailable(f"no events received yet (window up to {t1_us} µs asked)")
        if t1_us > self._watermark:
            raise WindowUnavailable(
                f"window [{t0_us}, {t1_us}) µs reaches past what is received: events are complete only "
                f"for t < {self._watermark} µs")

    def slice(self, t0_us: int, t1_us: int) -> Events:
        """A copy of the events with t0_us <= t < t1_us, complete or not at all (``WindowUnavailable``)."""
        t0_us, t1_us = int(t0_us), int(t1_us)
        if t1_us < t0_us:
            raise InvalidInputError(f"window end {t1_us} µs is before its start {t0_us} µs")
        with self._lock:
            self._check_window(t0_us, t1_us)
            i0, i1 = self._search(t0_us), self._search(t1_us)
            return self._copy(i0, i1)

    def count(self, t0_us: int, t1_us: int) -> int:
        """Number of events in [t0_us, t1_us) without copying them (same availability rules as slice)."""
        with self._lock:
            self._check_window(int(t0_us), int(t1_us))
            return self._search(int(t1_us)) - self._search(int(t0_us))

    def first_time(self, t0_us: int, t1_us: int) -> int | None:
        """Timestamp of the oldest retained event with t0_us <= t < t1_us (None: there is none)."""
        with self._lock:
            i = self._search(int(t0_us))
            if i >= self._end:
                return None
            t = int(self._t[i % self.capacity])
            return t if t < int(t1_us) else None

    @property
    def head_us(self) -> int | None:
        with self._lock:
            return int(self._t[(self._end - 1) % self.capacity]) if self._end > self._start else None

    @property
    def oldest_us(self) -> int | None:
        with self._lock:
            return int(self._t[self._start % self.capacity]) if self._end > self._start else None

    @property
    def watermark_us(self) -> int | None:
        return self._watermark

    def __len__(self) -> int:
        return self._end - self._start

    def stats(self) -> RingStats:
        with self._lock:
            size = self._end - self._start
            head = int(self._t[(self._end - 1) % self.capacity]) if size else None
            oldest = int(self._t[self._start % self.capacity]) if size else None
            return RingStats(capacity=self.capacity, size=size, fill=size / self.capacity, head_us=head,
                             oldest_us=oldest, watermark_us=self._watermark, pushed=self._pushed,
                             overflowed=self._overflowed, expired=self._expired, late=self._late,
                             nbytes=self.capacity * BYTES_PER_EVENT)
