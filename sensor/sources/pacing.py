"""Pacing of replays: how fast, from where, and whether to loop. Shared by every replay."""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass

from edmcgs.errors import InvalidInputError, ReplayFormatError

MAX_DELAY_S = 86_400.0
"""A replay never waits longer than a day for its next batch: a longer gap is a corrupt timestamp
(time.sleep raised OverflowError on one, killing the ingest thread)."""


@dataclass(frozen=True)
class Pacing:
    """How a replay is played."""

    factor: float = 1.0
    """Real-time factor: 1.0 follows the wall clock, 2.0 plays twice as fast, 0 as fast as possible."""
    loop: bool = False
    """Start over at the end, shifting timestamps so that time keeps increasing."""
    start_offset_us: int = 0
    """Skip this much of the recording, counted from its first timestamp."""
    batch_us: int = 10_000
    """Recording time per batch that read() returns (10 ms: 100 batches per real second)."""

    def __post_init__(self) -> None:
        if not (isinstance(self.factor, int | float) and math.isfinite(self.factor) and self.factor >= 0):
            raise InvalidInputError(f"pacing factor must be a finite number >= 0, got {self.factor!r}")
        if int(self.start_offset_us) != self.start_offset_us or self.start_offset_us < 0:
            raise InvalidInputError(f"start_offset_us must be an integer >= 0, got {self.start_offset_us!r}")
        if int(self.batch_us) != self.batch_us or self.batch_us <= 0:
            raise InvalidInputError(f"batch_us must be a positive integer, got {self.batch_us!r}")


class Pacer:
    """Maps stream time to wall time: the first call fixes the origin, later calls sleep until due.

    A consumer slower than the factor is not caught up by skipping data: the replay simply runs late.
    ``clock`` and ``sleep`` are injectable so that tests run on a fake clock.
    """

    def __init__(self, factor: float, *, clock: Callable[[], float] = time.monotonic,
                 sleep: Callable[[float], None] = time.sleep) -> None:
        if not (math.isfinite(factor) and factor >= 0):
            raise InvalidInputError(f"pacing factor must be a finite number >= 0, got {factor!r}")
        self.factor = float(factor)
        self._clock, self._sleep = clock, sleep
        self._origin: tuple[float, int] | None = None
        self.slept_s = 0.0

    def wait_until(self, t_us: int) -> None:
        """Block until stream time ``t_us`` is due on the wall clock (no-op at factor 0)."""
        if self.factor == 0:
            return
        if self._origin is None:
            self._origin = (self._clock(), int(t_us))
            return
        wall0, t0 = self._origin
        delay = wall0 + (int(t_us) - t0) / 1e6 / self.factor - self._clock()
        if not math.isfinite(delay) or delay > MAX_DELAY_S:
            raise ReplayFormatError(f"timestamp {int(t_us)} µs is {delay:.3g} s ahead of the replay's "
                                    f"clock (started at {t0} µs): a corrupt timestamp")
        if delay > 0:
            self._sleep(delay)
            self.slept_s += delay

    def lag_s(self, t_us: int) -> float:
        """How far behind schedule stream time ``t_us`` is being delivered (seconds, >= 0)."""
        if self.factor == 0 or self._origin is None:
            return 0.0
        wall0, t0 = self._origin
        return max(0.0, self._clock() - (wall0 + (int(t_us) - t0) / 1e6 / self.factor))
