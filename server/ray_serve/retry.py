"""Which failures of a call to a scene replica are retried, and how long.

A replica that died (killed, out of memory, its node lost) fails the calls it held; Serve replaces it,
and the same call sent again reaches a live replica (another one at once, or the replacement once it
is up). Every call the gateway forwards is a read (GET, or a websocket session replayed from its
messages), so sending it again is safe. Anything else is the scene's own answer and is passed on.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Awaitable, Callable
from typing import TypeVar

from ray.exceptions import ActorDiedError, ActorUnavailableError, RayActorError
from ray.serve.exceptions import ReplicaUnavailableError

T = TypeVar("T")

RETRYABLE = (ActorDiedError, ActorUnavailableError, RayActorError, ReplicaUnavailableError)
RETRY_FOR_S = 60.0
"""How long a call keeps being retried: a lone replica's replacement must load the model and warm up."""
FIRST_DELAY_S = 0.02
MAX_DELAY_S = 1.0


def retryable(exc: BaseException) -> bool:
    """True for a replica's death (also when Ray wraps it as the cause of a task error)."""
    seen = 0
    while exc is not None and seen < 4:
        if isinstance(exc, RETRYABLE):
            return True
        exc, seen = exc.__cause__, seen + 1
    return False


class Retrier:
    """Runs a call again while it fails by a replica's death, with a doubling delay, for at most
    ``retry_for_s``; counts the retries (the gateway's ``/healthz`` reports them)."""

    def __init__(self, retry_for_s: float = RETRY_FOR_S):
        self.retry_for_s = retry_for_s
        self.retries = 0  # calls sent again, a stream's restarts included
        self.stream_restarts = 0  # relayed websocket sessions started again on another replica

    async def run(self, call: Callable[[], Awaitable[T]]) -> T:
        deadline = time.monotonic() + self.retry_for_s
        delay = FIRST_DELAY_S
        while True:
            try:
                return await call()
            except Exception as exc:
                if not retryable(exc) or time.monotonic() + delay > deadline:
                    raise
            self.retries += 1
            await asyncio.sleep(delay)
            delay = min(2 * delay, MAX_DELAY_S)
