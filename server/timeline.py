"""Two clocks: the stream's (times of the events in the ring) and the scene's (the checkpoint's).

A replay of the checkpoint's own recording shares the scene's clock on its first pass; when it
loops, the sensor layer shifts each pass by the recording's length P so that stream time keeps
increasing. A recording on another clock (or a live camera) is mapped by aligning its first time
with the scene's start. In every case

    scene(T) = scene_origin + (T - stream_origin) mod P        (no "mod P" without a loop)

and the stream time rendered for a scene time t is the most recent T <= the head with scene(T) = t:
the newest events for that instant. The *head* is the ring's watermark: every event before it has
arrived, so [tau, head) is a complete window.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Timeline:
    """The map from stream time to scene time (all int64 µs)."""

    stream_origin_us: int
    """A stream time that maps to ``scene_origin_us``."""
    scene_origin_us: int
    """The scene time of ``stream_origin_us``."""
    period_us: int | None = None
    """Length of one pass of a looping stream; None when the stream does not loop."""

    def __post_init__(self):
        if self.period_us is not None and self.period_us <= 0:
            raise ValueError(f"period_us must be > 0, got {self.period_us}")

    def scene_of(self, stream_us: int) -> int:
        """Scene time of stream time ``stream_us``."""
        d = int(stream_us) - self.stream_origin_us
        if self.period_us is not None:
            d %= self.period_us
        return self.scene_origin_us + d

    def pass_start(self, stream_us: int) -> int | None:
        """Stream time at which the pass holding ``stream_us`` began (None without a loop)."""
        if self.period_us is None:
            return None
        d = int(stream_us) - self.stream_origin_us
        return int(stream_us) - d % self.period_us

    def stream_of(self, scene_us: int, not_after_us: int) -> int:
        """The latest stream time T <= ``not_after_us`` with scene(T) = ``scene_us``.

        Without a loop this is the one stream time of ``scene_us``, which may lie after
        ``not_after_us`` (not streamed yet); the caller checks. With a loop, T may precede the stream's
        start when the first pass has not reached ``scene_us`` yet; the caller checks that too.
        """
        base = self.stream_origin_us + (int(scene_us) - self.scene_origin_us)
        if self.period_us is None:
            return base
        return base + ((int(not_after_us) - base) // self.period_us) * self.period_us
