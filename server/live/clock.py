"""The server's clock algebra, pure (no I/O, no wall clock): which instant and which events window a
scene time renders from, and what can be rendered now.

Two clocks: the stream's (times of the events in the ring) and the scene's (the checkpoint's).

A replay of the checkpoint's own recording shares the scene's clock on its first pass; when it
loops, the sensor layer shifts each pass by the recording's length P so that stream time keeps
increasing. A recording on another clock (or a live camera) is mapped by aligning its first time
with the scene's start. In every case

    scene(T) = scene_origin + (T - stream_origin) mod P        (no "mod P" without a loop)

and the stream time rendered for a scene time t is the most recent T <= the head with scene(T) = t:
the newest events for that instant. The *head* is the ring's watermark: every event before it has
arrived, so [tau, head) is a complete window.

tau(t), the anchor whose events window [tau, t) drives the deformation, is decided by ``TauRule``
alone: within the checkpoint's span its own anchors (the windows it was trained on), whatever frames
the stream carries; past the span's end, online anchors: the stream's frames, each predicted by the
event transition from the one before (the checkpoint's last anchor first) and corrected in the
background (``anchors``), so that a stream renders to its head however long it runs. The engine asks
``Timebase`` (timebase.py), which applies the rule.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from edmcgs.errors import WindowUnavailable
from edmcgs.protocol import TauSource, seconds_of


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


class TimeNotRenderable(WindowUnavailable):
    """A time that cannot be rendered now; ``valid_range`` is the protocol's map of what can (None until
    the engine fills it in)."""

    def __init__(self, message: str, valid_range: dict | None = None):
        super().__init__(message)
        self.valid_range = valid_range


@dataclass(frozen=True)
class Instant:
    """A renderable instant."""

    t_us: int
    """Scene time rendered (the checkpoint's clock)."""
    anchor_us: int
    """tau(t) on the scene clock."""
    window: tuple[int, int]
    """The half-open window [tau, T) on the ring's clock: the events of I_E."""


@dataclass(frozen=True)
class Span:
    """The checkpoint's span on the scene clock: from its first anchor to its end (µs, inclusive)."""

    first_us: int
    end_us: int

    def clip(self, lo: int | None, hi: int) -> list[tuple[int, int]]:
        """[lo, hi] clipped to the span, as a list of zero or one interval."""
        if lo is None:
            return []
        lo, hi = max(lo, self.first_us), min(hi, self.end_us)
        return [(lo, hi)] if lo <= hi else []


@dataclass(frozen=True)
class TauRule:
    """Where tau(t) comes from, by scene time: the one place that decides it.

    A checkpoint was trained on the windows [tau, t) from its own anchors (``meta.anchors_us``, the
    scene clock) to every time of its span, the last anchor's window running to the span's end; the
    stream's frames (a replay's every APS frame, a camera's) may be denser or elsewhere. Within the
    span the checkpoint's anchors rule, so that a replay of the checkpoint's own recording renders
    what ``edmcgs eval`` scores. Past the span's end, with ``online``, the stream's frames become
    online anchors (``TauSource.ONLINE``: the newest online anchor before t, the checkpoint's last
    anchor until the first one), up to the head. ``stream_frames`` without ``online`` (an anchor store
    only) names the stream's frames as the source outside the span, where nothing renders.
    """

    checkpoint: Span
    """The span the checkpoint's anchors cover (scene clock)."""
    stream_frames: bool
    """Whether the stream delivers frames (an anchor store is filled)."""
    online: bool = False
    """Whether the stream's frames past the span become online anchors (anchors.py)."""

    def source(self, scene_t: int) -> TauSource | None:
        """Where tau comes from at ``scene_t``; None: no anchor rules there."""
        if self.checkpoint.first_us <= int(scene_t) <= self.checkpoint.end_us:
            return TauSource.CHECKPOINT
        if self.online and int(scene_t) > self.checkpoint.end_us:
            return TauSource.ONLINE
        return TauSource.STREAM if self.stream_frames else None

    def end(self, head_scene_us: int | None) -> int:
        """The last scene time that may be rendered: the span's end, or the head past it when online."""
        if self.online and head_scene_us is not None:
            return max(self.checkpoint.end_us, int(head_scene_us))
        return self.checkpoint.end_us

    def ranges(self, head_scene_us: int | None = None) -> list[tuple[TauSource, int, int]]:
        """The renderable scene times by tau source: (source, first µs, last µs inclusive), in order."""
        out = [(TauSource.CHECKPOINT, self.checkpoint.first_us, self.checkpoint.end_us)]
        if self.online and head_scene_us is not None and head_scene_us > self.checkpoint.end_us:
            out.append((TauSource.ONLINE, self.checkpoint.end_us + 1, int(head_scene_us)))
        return out


@dataclass(frozen=True)
class Query:
    """A scene time asked for, placed on the stream's clock (``locate``)."""

    t_us: int
    """The scene time (the head's when none was asked for)."""
    stream_t: int
    """The stream time rendered for it: the newest one <= the head with that scene time."""
    what: str
    """How messages name it."""


def fmt(t_us: int, origin_us: int) -> str:
    """A scene time as messages write it: seconds from the scene's start ``origin_us``, and the µs."""
    return f"{seconds_of(t_us, origin_us):.6f} s (t_us={t_us})"


def locate(t_us: int | None, head_stream_us: int, timeline: Timeline, span: Span, origin_us: int,
           online_end_us: int | None = None) -> Query:
    """Scene time ``t_us`` (None: the head) on the stream clock, or TimeNotRenderable saying why.

    head_stream_us: the head on the stream clock (every event before it has arrived); origin_us: the
    scene's start, for messages; online_end_us: with online anchors, the last renderable scene time past
    the span (TauRule.end), which replaces the span's end.
    """
    tl = timeline
    if online_end_us is not None:
        span = Span(span.first_us, max(span.end_us, int(online_end_us)))
    if t_us is None:
        t_us, stream_t = tl.scene_of(head_stream_us), head_stream_us
        what = f"the head of the stream (scene time {fmt(t_us, origin_us)})"
    else:
        t_us = int(t_us)
        stream_t = tl.stream_of(t_us, head_stream_us)
        what = f"t={fmt(t_us, origin_us)}"
    if not span.first_us <= t_us <= span.end_us:
        first, end = fmt(span.first_us, origin_us), fmt(span.end_us, origin_us)
        raise TimeNotRenderable(f"{what} is outside the checkpoint's span: the first anchor is at {first} "
                                f"and the span ends at {end}" if online_end_us is None else
                                f"{what} is outside what can be rendered: the first anchor is at {first} "
                                f"and the stream's head is at {end}")
    if stream_t > head_stream_us or (tl.period_us is not None and stream_t < tl.stream_origin_us):
        raise TimeNotRenderable(f"{what} has not been streamed yet")
    return Query(t_us, stream_t, what)


def instant(query: Query, anchor_stream: int | None, timeline: Timeline, span: Span,
            origin_us: int) -> Instant:
    """The instant rendered for ``query`` from its anchor tau (``anchor_stream``, on the stream clock; None:
    no anchor precedes it), or TimeNotRenderable saying why its window is not complete."""
    tl, t_us, stream_t = timeline, query.t_us, query.stream_t
    a_scene = t_us - (stream_t - anchor_stream) if anchor_stream is not None else None
    if a_scene is None or a_scene < span.first_us:
        raise TimeNotRenderable(f"{query.what}: no anchor frame of this pass of the stream precedes it yet")
    if tl.period_us is not None and anchor_stream < tl.pass_start(stream_t):
        # A looping stream restarts at the pass start: a window reaching before it would mix in the
        # end of the previous pass.
        raise TimeNotRenderable(f"{query.what}: its anchor at {fmt(a_scene, origin_us)} precedes the start "
                                f"of the looping stream's pass ({fmt(tl.scene_origin_us, origin_us)})")
    return Instant(t_us, a_scene, (anchor_stream, stream_t))


def renderable(head_stream_us: int, timeline: Timeline, span: Span, anchors: np.ndarray,
               oldest_us: int | None, dropped: bool) -> list[tuple[int, int]]:
    """Scene-time intervals [lo, hi] (µs, inclusive) that can be rendered now, oldest first.

    head_stream_us: the head on the stream clock; anchors: anchor times on the scene clock, sorted;
    oldest_us: the oldest event time the ring retains (None: none); dropped: whether the ring has
    dropped events (overflow or expiry), so that its oldest retained time bounds every window.
    """
    tl, wm = timeline, head_stream_us
    s_wm = tl.scene_of(wm)
    if dropped:
        if oldest_us is None:
            return []  # everything received was dropped
        floor = oldest_us + 1  # a window starting at the oldest retained time may miss events dropped there
    else:  # nothing dropped: all since the stream's start (an empty window is complete too)
        floor = tl.stream_origin_us if oldest_us is None else min(oldest_us, tl.stream_origin_us)
    s_floor = tl.scene_of(floor)

    def first_anchor_from(s: int) -> int | None:
        i = int(np.searchsorted(anchors, s, side="left"))
        return int(anchors[i]) if i < len(anchors) else None

    p_wm, p_floor = tl.pass_start(wm), tl.pass_start(floor)
    if p_wm is None or p_wm == p_floor:
        return span.clip(first_anchor_from(s_floor), s_wm)
    current = span.clip(first_anchor_from(tl.scene_origin_us), s_wm)
    if p_wm - p_floor >= 2 * tl.period_us:
        # A whole earlier pass is retained: every time whose anchor lies within a pass.
        return span.clip(first_anchor_from(tl.scene_origin_us), span.end_us)
    previous = span.clip(first_anchor_from(s_floor), span.end_us)
    if current and previous and previous[0][0] <= current[0][1] + 1:
        return [(current[0][0], max(current[0][1], previous[0][1]))]
    return previous + current


def playback_watermark(first_us: int, period_us: int, elapsed_us: int, speed: float) -> int:
    """The watermark of a sensorless playback ``elapsed_us`` wall µs after it started.

    The stream is taken to have begun two passes before the clock starts: at elapsed 0 the head
    (watermark - 1) is scene time ``first_us`` on the third pass, so a whole earlier pass counts as
    delivered and the whole span is renderable from the first request on.
    """
    return int(first_us) + 2 * int(period_us) + 1 + int(elapsed_us * speed)

