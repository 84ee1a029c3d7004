"""Bounded render concurrency: a thread pool of ``workers`` plus at most ``queue`` renders waiting.

Renders run in threads because the heavy parts release the GIL (torch ops, the numba rasterizer
compiled ``nogil=True``), so two cores serve two renders at once while the event loop stays free.
A GET /render beyond workers + queue is refused at once (503, Retry-After) rather than queued
without bound; a websocket stream waits for a slot instead (its frames are paced and dropped on
their own).
"""

from __future__ import annotations

import asyncio
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from typing import TypeVar

from edmcgs.server.errors import Busy

T = TypeVar("T")


class RenderPool:
    """Runs blocking render callables off the event loop, at most ``workers + queue`` admitted at once."""

    def __init__(self, workers: int, queue: int):
        self.capacity = workers + queue
        self.rejected = 0
        self.in_flight = 0  # admitted and not finished: running or waiting for a worker
        self._executor = ThreadPoolExecutor(workers, thread_name_prefix="edmcgs-render")
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

    def close(self) -> None:
        """Finish running renders, drop queued ones, free the threads."""
        self._executor.shutdown(wait=True, cancel_futures=True)
