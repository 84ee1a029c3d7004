"""The render engine: (time, pose, size) -> pixels, from the model, the event ring and the anchors.

    t ──> stream window [tau, T) on the ring's clock (timeline.py) ──> events ──> I_E
      ──> model.deform(t, I_E)            (pose-independent: cached, computed once per instant)
      ──> model.render(state, pose, K)    (per client; numba fast path, off the event loop)

Every method here blocks; the routes call them on the render pool's threads.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from edmcgs.errors import InvalidInputError, WindowUnavailable
from edmcgs.geometry import Intrinsics
from edmcgs.model.dynamic import EdMCGS
from edmcgs.sensor.buffer.anchors import AnchorStore
from edmcgs.sensor.buffer.ring import EventRingBuffer
from edmcgs.sensor.event_map import accumulate
from edmcgs.sensor.events import Events
from edmcgs.server.encode import to_uint8
from edmcgs.server.playback import Playback
from edmcgs.server.state_cache import StateCache
from edmcgs.server.timeline import Timeline


class TimeNotRenderable(WindowUnavailable):
    """A time that cannot be rendered now; ``valid_range`` is the protocol's map of what can."""

    def __init__(self, message: str, valid_range: dict | None):
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
    """[tau, T) on the ring's clock: the events of I_E."""


@dataclass(frozen=True)
class Rendered:
    pixels: np.ndarray  # uint8 [H, W, C]
    instant: Instant
    events: int


class Engine:
    """Owns nothing it did not build: the model, ring and anchors are passed in (the app's lifespan
    opens and closes them). ``timeline`` is set once the stream's clock is known (at once for a
    replay, at the first event for a camera).

    model: the loaded EdMCGS; ring: the event ring the ingest thread fills (without a sensor: an empty
    one); anchors: the source's frames, or None to use the checkpoint's anchor times; cache_size:
    deformed states kept; raster_threads: threads of the numba rasterizer per render (None: numba's
    default, all cores); playback: without a sensor, the clock that moves the head (playback.py).
    """

    def __init__(self, model: EdMCGS, ring: EventRingBuffer, anchors: AnchorStore | None, *,
                 cache_size: int = 32, raster_threads: int | None = None, playback: Playback | None = None):
        self.model = model
        self.meta = model.meta
        self.ring = ring
        self.anchors = anchors
        self.playback = playback
        self.timeline: Timeline | None = None if playback is None else playback.timeline
        self.cache = StateCache(cache_size)
        self.scene_anchors = np.asarray(self.meta.anchors_us, dtype=np.int64)
        self.first_us = int(self.scene_anchors[0])  # the Markov chain has no state before it
        self.end_us = int(self.meta.t_end_us)
        # The numba rasterizer on a CPU; the torch one where the model lives on a GPU.
        self.fast = model.center.device.type == "cpu"
        self.raster_threads = raster_threads

    # ------------------------------------------------------------------ time
    def t_us_of_seconds(self, t: float) -> int:
        """Seconds from the scene's start -> absolute scene µs."""
        return self.meta.t_start_us + round(t * 1e6)

    def seconds_of(self, t_us: int) -> float:
        return (int(t_us) - self.meta.t_start_us) / 1e6

    def head(self) -> tuple[int, int] | None:
        """(stream µs, scene µs) of the head: the newest time whose events and anchor have all arrived.

        The ring's watermark W says every event with t < W is in; a source delivers the frames of
        [.., W) with those events, so an anchor exactly at W may still be coming: the head is W - 1.
        Without a sensor the playback clock completes the (empty) stream up to now.
        """
        if self.playback is not None:
            self.ring.mark_complete(self.playback.watermark_us())
        wm, tl = self.ring.watermark_us, self.timeline
        if wm is None or tl is None:
            return None
        return wm - 1, tl.scene_of(wm - 1)

    def resolve(self, t_us: int | None) -> Instant:
        """The instant rendered for scene time ``t_us`` (None: the head), or TimeNotRenderable."""
        head = self.head()
        if head is None:
            raise TimeNotRenderable("no events have arrived yet; retry in a moment", None)
        wm, head_scene = head
        tl = self.timeline
        if t_us is None:
            t_us, stream_t = head_scene, wm
            what = f"the head of the stream (scene time {self._fmt(t_us)})"
        else:
            t_us = int(t_us)
            stream_t = tl.stream_of(t_us, wm)
            what = f"t={self._fmt(t_us)}"
        if not self.first_us <= t_us <= self.end_us:
            self._unavailable(f"{what} is outside the checkpoint's span: the first anchor is at "
                              f"{self._fmt(self.first_us)} and the span ends at {self._fmt(self.end_us)}")
        if stream_t > wm or (tl.period_us is not None and stream_t < tl.stream_origin_us):
            self._unavailable(f"{what} has not been streamed yet")
        a_stream = self._anchor_stream(stream_t, t_us)
        a_scene = t_us - (stream_t - a_stream) if a_stream is not None else None
        if a_scene is None or a_scene < self.first_us:
            self._unavailable(f"{what}: no anchor frame of this pass of the stream precedes it yet")
        return Instant(t_us, a_scene, (a_stream, stream_t))

    def _anchor_stream(self, stream_t: int, scene_t: int) -> int | None:
        """tau on the stream clock: the source's frames when it has them, else the checkpoint's anchors."""
        if self.anchors is not None:
            try:
                return self.anchors.tau(stream_t)
            except WindowUnavailable as exc:
                self._unavailable(str(exc))
        i = int(np.searchsorted(self.scene_anchors, scene_t, side="right")) - 1
        return None if i < 0 else stream_t - (scene_t - int(self.scene_anchors[i]))

    # ------------------------------------------------------------------ what can be rendered
    def renderable(self) -> list[tuple[int, int]]:
        """Scene-time intervals [lo, hi] (µs, inclusive) that can be rendered now, oldest first."""
        head = self.head()
        if head is None:
            return []
        wm, s_wm = head
        tl = self.timeline
        stats = self.ring.stats()
        oldest = stats.oldest_us
        if stats.overflowed or stats.expired:
            if oldest is None:
                return []  # everything received was dropped
            floor = oldest + 1  # a window starting at the oldest retained time may miss events dropped there
        else:  # nothing dropped: all since the stream's start (an empty window is complete too)
            floor = tl.stream_origin_us if oldest is None else min(oldest, tl.stream_origin_us)
        s_floor = tl.scene_of(floor)
        anchors = self._scene_anchor_times()

        def first_anchor_from(s: int) -> int | None:
            i = int(np.searchsorted(anchors, s, side="left"))
            return int(anchors[i]) if i < len(anchors) else None

        def clip(lo: int | None, hi: int) -> list[tuple[int, int]]:
            if lo is None:
                return []
            lo, hi = max(lo, self.first_us), min(hi, self.end_us)
            return [(lo, hi)] if lo <= hi else []

        p_wm, p_floor = tl.pass_start(wm), tl.pass_start(floor)
        if p_wm is None or p_wm == p_floor:
            return clip(first_anchor_from(s_floor), s_wm)
        current = clip(first_anchor_from(tl.scene_origin_us), s_wm)
        if p_wm - p_floor >= 2 * tl.period_us:
            return clip(self.first_us, self.end_us)  # a whole earlier pass is retained
        previous = clip(first_anchor_from(s_floor), self.end_us)
        if current and previous and previous[0][0] <= current[0][1] + 1:
            return [(current[0][0], max(current[0][1], previous[0][1]))]
        return previous + current

    def _scene_anchor_times(self) -> np.ndarray:
        if self.anchors is None or self.timeline is None:
            return self.scene_anchors
        return np.unique([self.timeline.scene_of(int(a)) for a in self.anchors.times()]).astype(np.int64)

    def valid_range(self) -> dict | None:
        """The protocol's ``valid_range``: the most recent renderable interval."""
        ranges = self.renderable()
        return self.range_dict(ranges[-1]) if ranges else None

    def range_dict(self, interval: tuple[int, int]) -> dict:
        lo, hi = interval
        return {"t_min": self.seconds_of(lo), "t_max": self.seconds_of(hi), "t_us_min": lo, "t_us_max": hi}

    def _unavailable(self, message: str):
        ranges = self.renderable()
        if ranges:
            listed = ", ".join(f"[{self.seconds_of(a):.6f}, {self.seconds_of(b):.6f}] s "
                               f"(t_us [{a}, {b}])" for a, b in ranges)
            message += f"; renderable now: {listed}"
        else:
            message += "; nothing is renderable yet"
        raise TimeNotRenderable(message, self.range_dict(ranges[-1]) if ranges else None)

    def _fmt(self, t_us: int) -> str:
        return f"{self.seconds_of(t_us):.6f} s (t_us={t_us})"

    # ------------------------------------------------------------------ deformation and render
    def state(self, instant: Instant) -> tuple[object, int]:
        """(GaussianState at the instant, events in its window), shared by all clients (cached)."""
        key = (instant.t_us, instant.anchor_us, instant.window)
        return self.cache.get(key, lambda: self._deform(instant))

    def _deform(self, instant: Instant) -> tuple[object, int]:
        try:
            events = self.ring.slice(*instant.window)
        except WindowUnavailable as exc:
            self._unavailable(f"the events for t={self._fmt(instant.t_us)} are gone: {exc}")
        emap = None
        if self.meta.has_event_branch and len(events):
            emap = accumulate(events, self.meta.event_width, self.meta.event_height)
        return self.model.deform(instant.t_us, emap), len(events)

    def default_pose(self, t_us: int) -> np.ndarray:
        """The event camera's own pose at scene time ``t_us`` (the checkpoint's trajectory)."""
        if self.meta.trajectory is None:
            raise InvalidInputError("pose is required: this checkpoint has no camera trajectory")
        return self.meta.trajectory.at(int(t_us))

    def intrinsics(self, width: int, height: int) -> Intrinsics:
        native = self.meta.intrinsics
        if (width, height) == (native.width, native.height):
            return native
        return native.scaled(width, height)

    def render(self, t_us: int | None, pose: np.ndarray | None, width: int, height: int) -> Rendered:
        """Pixels of the scene at ``t_us`` (None: the head) from ``pose`` (None: the event camera's)."""
        instant = self.resolve(t_us)
        state, n_events = self.state(instant)
        c2w = self.default_pose(instant.t_us) if pose is None else pose
        intr = self.intrinsics(width, height)
        image = self.model.render(state, c2w, intr, fast=self.fast, threads=self.raster_threads)
        return Rendered(to_uint8(image), instant, n_events)

    def warm_up(self) -> float:
        """Compile the fast paths (numba) with one render at the first anchor, off the request path.

        Returns the seconds it took.
        """
        t0 = time.perf_counter()
        state = self.model.deform(self.first_us, None)
        c2w = self.default_pose(self.first_us) if self.meta.trajectory is not None else np.eye(4)
        self.model.render(state, c2w, self.meta.intrinsics, fast=self.fast, threads=self.raster_threads)
        one = Events(np.zeros(1, np.int64), np.zeros(1, np.uint16), np.zeros(1, np.uint16),
                     np.ones(1, np.int8))
        emap = accumulate(one, self.meta.event_width, self.meta.event_height)
        if self.meta.has_event_branch and self.end_us > self.first_us:
            self.model.deform(self.first_us + 1, emap)  # past the anchor: at it the branch is skipped
        return time.perf_counter() - t0
