"""Bounded render concurrency, with separate capacity for single renders and for streams.

Single renders (GET /render): a thread pool of ``workers`` plus at most ``queue`` renders waiting; one
beyond that is refused at once (503, Retry-After) rather than queued without bound.

Stream frames (WS /stream): their own ``stream_workers`` threads, never a slot of the single renders
(ten streams used to hold every worker and queue slot, so that every GET /render answered 503). A
stream renders one frame at a time (its producer awaits each), so at most one waiting frame per open
stream, and the number of streams is capped by the settings; a stream's frames are paced and dropped
on their own (latest wins) when its renders fall behind.

Renders run in threads because the heavy parts release the GIL (torch ops, the numba rasterizer
compiled ``nogil=True``), so two cores serve two renders at once while the event loop stays free.
"""

from __future__ import annotations

import asyncio
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from typing import TypeVar

from edmcgs.server.errors import Busy

T = TypeVar("T")


class RenderPool:
    """Runs blocking render callables off the event loop: single renders at most ``workers + queue``
    admitted at once, stream frames on ``stream_workers`` threads of their own."""

    def __init__(self, workers: int, queue: int, stream_workers: int = 1):
        self.capacity = workers + queue
        self.rejected = 0
        self.in_flight = 0  # single renders admitted and not finished: running or waiting for a worker
        self.stream_in_flight = 0  # stream frames running or waiting for a stream worker
        self._executor = ThreadPoolExecutor(workers, thread_name_prefix="edmcgs-render")
        self._stream_executor = ThreadPoolExecutor(stream_workers, thread_name_prefix="edmcgs-stream")
        self._slots = asyncio.Semaphore(self.capacity)

    async def run(self, fn: Callable[[], T], *, wait: bool = False) -> T:
        """``fn()`` on a worker thread. ``wait=False``: raise Busy when every slot is taken."""
        if not wait and self._slots.locked():
            self.rejected += 1
            raise Busy(retry_after_s=1)
        async with self._slots:
            self.in_flight += 1
            try:
                return await asyncio.get_running_loop().run_in_executor(self._executor, fn)
            finally:
                self.in_flight -= 1

    async def run_stream(self, fn: Callable[[], T]) -> T:
        """``fn()`` on a stream worker (the caller awaits it: one frame at a time per stream)."""
        self.stream_in_flight += 1
        try:
            return await asyncio.get_running_loop().run_in_executor(self._stream_executor, fn)
        finally:
            self.stream_in_flight -= 1

    def close(self) -> None:
        """Finish running renders, drop queued ones, free the threads."""
        self._executor.shutdown(wait=True, cancel_futures=True)
        self._stream_executor.shutdown(wait=True, cancel_futures=True)
