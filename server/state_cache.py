"""A small LRU of deformed Gaussian states, computed once however many clients ask at once.

The deformation at t (event map, CNN, MLP, skinning) does not depend on the viewing pose, so
clients looking at the same instant from different poses share it. Keys identify the inputs exactly:
(t_us, anchor_us, event window in stream time, event count); the ring never rewrites retained events.
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from collections.abc import Callable, Hashable
from concurrent.futures import Future
from typing import Any


class StateCache:
    """LRU of ``size`` entries with single flight: concurrent ``get`` calls for one key compute it once."""

    def __init__(self, size: int):
        if size < 1:
            raise ValueError(f"size must be >= 1, got {size}")
        self.size = size
        self.hits = 0
        self.misses = 0
        self._lock = threading.Lock()
        self._entries: OrderedDict[Hashable, Any] = OrderedDict()
        self._pending: dict[Hashable, Future] = {}

    def get(self, key: Hashable, compute: Callable[[], Any]) -> Any:
        """The value for ``key``, calling ``compute()`` only if no one has it or is computing it.

        An exception from ``compute`` reaches every caller waiting on that key and is not cached.
        """
        with self._lock:
            if key in self._entries:
                self._entries.move_to_end(key)
                self.hits += 1
                return self._entries[key]
            future = self._pending.get(key)
            owner = future is None
            if owner:
                future = self._pending[key] = Future()
                self.misses += 1
            else:
                self.hits += 1
        if not owner:
            return future.result()
        try:
            value = compute()
        except BaseException as exc:
            with self._lock:
                del self._pending[key]
            future.set_exception(exc)
            raise
        with self._lock:
            self._entries[key] = value
            while len(self._entries) > self.size:
                self._entries.popitem(last=False)
            del self._pending[key]
        future.set_result(value)
        return value

    def __len__(self) -> int:
        with self._lock:
            return len(self._entries)
