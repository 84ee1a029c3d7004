"""What the websocket's live mode needs from the ingest thread: a wake-up when new events are stored,
and when they arrived (for the event-to-frame latency each live frame reports).
"""

from __future__ import annotations

import asyncio
import threading
import time
from collections import deque
from collections.abc import Callable


class HeadSignal:
    """Wakes every waiting coroutine when the ingest thread stores a batch. ``notify`` is thread-safe."""

    def __init__(self, loop: asyncio.AbstractEventLoop):
        self._loop = loop
        self._event = asyncio.Event()

    def notify(self) -> None:
        """Called from the ingest thread."""
        try:
            self._loop.call_soon_threadsafe(self._fire)
        except RuntimeError:  # the loop closed during shutdown: nobody is waiting any more
            pass

    def _fire(self) -> None:
        self._event.set()
        self._event = asyncio.Event()

    async def wait(self, timeout: float) -> bool:
        """Return at the next notify (True), or after ``timeout`` seconds (False)."""
        try:
            await asyncio.wait_for(self._event.wait(), timeout)
        except TimeoutError:
            return False
        return True


class Arrivals:
    """Wall-clock arrival of the newest batches: (stream time complete up to, Unix µs), bounded."""

    def __init__(self, keep: int = 4096, clock: Callable[[], int] = lambda: time.time_ns() // 1000):
        self._items: deque[tuple[int, int]] = deque(maxlen=keep)
        self._lock = threading.Lock()
        self._clock = clock  # Unix µs

    def record(self, complete_until_us: int) -> None:
        """Called by the ingest thread right after a batch reached the ring."""
        with self._lock:
            self._items.append((int(complete_until_us), int(self._clock())))

    def arrival_of(self, stream_us: int) -> int | None:
        """Unix µs at which the batch holding stream time ``stream_us`` arrived: the first one complete
        beyond it (None: not arrived yet; the oldest batch kept when it is forgotten). Given a live
        frame's oldest new event, that batch has waited longest: it measures the frame's event-to-frame
        latency.
        """
        with self._lock:
            found = None
            for until, unix_us in reversed(self._items):
                if until <= stream_us:
                    break
                found = unix_us
            return found
