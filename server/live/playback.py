"""The clock of a server without a sensor: the checkpoint's span played in a loop at wall-clock speed.

A checkpoint without an event branch needs no events, so every time of its span renders at once and
nothing is ingested. What a sensor's stream gives the engine, a head that moves, comes from this clock
instead: its stream time is the wall-clock time since the service opened (times ``speed``), looping over
the span like a looping replay (see clock.py), so the head (GET /render without t, the websocket's
live mode, the viewer) plays the scene. The stream is taken to have begun two passes before the
clock starts: a whole earlier pass counts as delivered, and the renderable range is the whole span from
the first request on (``Engine.renderable``).
"""

from __future__ import annotations

import time

from edmcgs.server.live.clock import Timeline, playback_watermark


class Playback:
    """first_us, end_us: the span (scene µs, inclusive, from the first anchor); speed: real-time factor."""

    def __init__(self, first_us: int, end_us: int, speed: float = 1.0):
        if end_us < first_us:
            raise ValueError(f"the span ends ({end_us}) before it starts ({first_us})")
        if not speed > 0:
            raise ValueError(f"speed must be > 0, got {speed}")
        self.period_us = int(end_us) - int(first_us) + 1
        self.timeline = Timeline(int(first_us), int(first_us), self.period_us)
        self.speed = float(speed)
        self.first_us = int(first_us)
        self._start_ns = time.monotonic_ns()

    def watermark_us(self) -> int:
        """Stream time up to which the (empty) stream is complete: now on this clock."""
        elapsed_us = (time.monotonic_ns() - self._start_ns) // 1000
        return playback_watermark(self.first_us, self.period_us, elapsed_us, self.speed)
