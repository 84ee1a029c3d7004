"""The render engine: (time, pose, size) -> pixels, from the model, the event ring and the anchors.

    t ──> stream window [tau, T) on the ring's clock (clock.py, pure) ──> events ──> I_E
      ──> model.deform(t, I_E)            (pose-independent: cached, computed once per instant)
      ──> model.render(state, pose, K)    (per client; numba fast path, off the event loop)

Every method here blocks; the routes call them on the render pool's threads.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from edmcgs import protocol
from edmcgs.errors import InvalidInputError, WindowUnavailable
from edmcgs.geometry import Intrinsics
from edmcgs.model import event_bounds
from edmcgs.model import online as model_online
from edmcgs.model.dynamic import EdMCGS
from edmcgs.protocol import TauSource
from edmcgs.sensor.buffer.anchors import AnchorStore
from edmcgs.sensor.buffer.ring import EventRingBuffer
from edmcgs.sensor.event_map import accumulate
from edmcgs.sensor.events import Events
from edmcgs.server import clock
from edmcgs.server.clock import Instant, Span, Timeline, TimeNotRenderable
from edmcgs.server.encode import to_uint8
from edmcgs.server.online import OnlineAnchors
from edmcgs.server.playback import Playback
from edmcgs.server.state_cache import StateCache

CAMERA_POSE_ATOL = 1e-5
"""A pose given whose entries (rotation, translation in m) are all within this of the event camera's
own is its view: at the DAVIS346's focal length (~300 px), a hundredth of a pixel at most."""


@dataclass(frozen=True)
class Rendered:
    pixels: np.ndarray  # uint8 [H, W, C]
    instant: Instant
    events: int
    anchor: str = "checkpoint"
    """protocol.ANCHOR_KINDS: the checkpoint's anchor, or an online one predicted or corrected."""
    stages: dict[str, float] = field(default_factory=dict)
    """Seconds spent per stage: "state" (the events and the deformation, or a cache hit), "raster",
    "project"."""
    projected: bool = False
    """Projected onto the events since the anchor's frame (``Engine._frame``)."""


class Engine:
    """Owns nothing it did not build: the model, ring and anchors are passed in (the app's lifespan
    opens and closes them). ``timeline`` is set once the stream's clock is known (at once for a
    replay, at the first event for a camera).

    model: the loaded EdMCGS; ring: the event ring the ingest thread fills (without a sensor: an empty
    one); anchors: the source's frames (None: it has none), tau only where the checkpoint has no
    anchor (``tau_rule``, clock.TauRule); cache_size:
    deformed states kept; raster_threads: threads of the numba rasterizer per render (None: numba's
    default, all cores); playback: without a sensor, the clock that moves the head (playback.py);
    online: the online anchors past the span (online.py; None: the span's end is the last time).
    """

    def __init__(self, model: EdMCGS, ring: EventRingBuffer, anchors: AnchorStore | None, *,
                 cache_size: int = 32, raster_threads: int | None = None, playback: Playback | None = None,
                 online: OnlineAnchors | None = None):
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
        self.span = Span(self.first_us, self.end_us)
        self.online = online
        self.tau_rule = clock.TauRule(self.span, stream_frames=anchors is not None or online is not None,
                                      online=online is not None)
        # The numba rasterizer on a CPU; the torch one where the model lives on a GPU.
        self.fast = model.center.device.type == "cpu"
        self.raster_threads = raster_threads

    # ------------------------------------------------------------------ time
    def t_us_of_seconds(self, t: float) -> int:
        """Seconds from the scene's start -> absolute scene µs."""
        return protocol.t_us_of_seconds(t, self.meta.t_start_us)

    def seconds_of(self, t_us: int) -> float:
        return protocol.seconds_of(t_us, self.meta.t_start_us)

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
        try:
            return clock.resolve(t_us, head[0], self.timeline, self.span, self._anchor_stream, self._fmt,
                                 self.tau_rule.end(head[1]) if self.online is not None else None)
        except TimeNotRenderable as exc:
            self._unavailable(str(exc))

    def _anchor_stream(self, stream_t: int, scene_t: int) -> int | None:
        """tau on the stream clock, from where ``tau_rule`` says: the checkpoint's anchors or the
        stream's frames."""
        source = self.tau_rule.source(scene_t)
        if source is TauSource.CHECKPOINT:
            return clock.scene_anchor_stream(self.scene_anchors, stream_t, scene_t)
        if source is TauSource.ONLINE:
            return self.online.tau(stream_t, scene_t)
        if source is TauSource.STREAM and self.anchors is not None:
            try:
                return self.anchors.tau(stream_t)
            except WindowUnavailable as exc:
                raise TimeNotRenderable(str(exc)) from None
        return None

    def tau_ranges(self) -> list[dict]:
        """GET /scene's ``tau_sources``: where tau comes from, by range of scene time (protocol.py)."""
        return [{"source": source.value, **self.range_dict((lo, hi))}
                for source, lo, hi in self.tau_rule.ranges(self._head_scene())]

    def _head_scene(self) -> int | None:
        head = self.head()
        return None if head is None else head[1]

    # ------------------------------------------------------------------ what can be rendered
    def renderable(self) -> list[tuple[int, int]]:
        """Scene-time intervals [lo, hi] (µs, inclusive) that can be rendered now, oldest first."""
        head = self.head()
        if head is None:
            return []
        stats = self.ring.stats()
        dropped = bool(stats.overflowed or stats.expired)
        # Within the checkpoint's span tau comes from its anchors (``tau_rule``).
        ranges = clock.renderable(head[0], self.timeline, self.span, self.scene_anchors,
                                  stats.oldest_us, dropped)
        if self.online is None or head[1] <= self.end_us:
            return ranges
        # Past the span, up to the head: from the checkpoint's last anchor of this pass, or from the
        # oldest online anchor whose events the ring still holds.
        floor = (stats.oldest_us + 1 if stats.oldest_us is not None else None) if dropped else None
        last_ckpt_stream = head[0] - (head[1] - int(self.scene_anchors[-1]))
        if floor is None or last_ckpt_stream >= floor:
            lo = self.end_us + 1
        else:
            lo = next((a.t_us for a in self.online.anchors()
                       if a.stream_us >= floor and a.stream_us > last_ckpt_stream), None)
            if lo is None:
                return ranges
        if ranges and ranges[-1][1] + 1 >= lo:
            return [*ranges[:-1], (ranges[-1][0], head[1])]
        return [*ranges, (lo, head[1])]

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
        return self._entry(instant)[:2]

    def _entry(self, instant: Instant) -> tuple[object, int, np.ndarray | None]:
        """``state``'s pair and the window's I_E (None: no events, or none needed) (cached)."""
        online = self.online.get(instant.window[0]) if self.online is not None else None
        key = (instant.t_us, instant.anchor_us, instant.window,
               None if online is None else (online.version, self.online.transition_version))
        return self.cache.get(key, lambda: self._deform(instant, online))

    def anchor_kind(self, instant: Instant) -> str:
        """protocol.ANCHOR_KINDS of the instant's anchor."""
        online = self.online.get(instant.window[0]) if self.online is not None else None
        return "checkpoint" if online is None else "corrected" if online.corrected else "predicted"

    def _deform(self, instant: Instant, online=None) -> tuple[object, int, np.ndarray | None]:
        try:
            events = self.ring.slice(*instant.window)
        except WindowUnavailable as exc:
            self._unavailable(f"the events for t={self._fmt(instant.t_us)} are gone: {exc}")
        emap = None  # the model's input, and past the span what a render is projected onto (_frame)
        if (self.meta.has_event_branch or instant.t_us > self.end_us) and len(events):
            emap = accumulate(events, self.meta.event_width, self.meta.event_height)
        if online is not None:  # from the online anchor's state, by the events since it (model/online.py)
            try:
                c2w = self.default_pose(instant.t_us)
            except InvalidInputError:  # no trajectory and no frame poses: global sampling only
                c2w = None
            motion = self.online.advance(online.motion, emap, c2w)
            state = model_online.with_spawned(model_online.state_of(self.model, motion, online.colors),
                                              online.spawned)
            return state, len(events), emap
        return self.model.deform(instant.t_us, emap), len(events), emap

    def event_map(self, t_us: int | None) -> tuple[Instant, int, np.ndarray]:
        """(instant, events, I_E) of the window a render at ``t_us`` (None: the head) uses: the signed
        polarity sum per pixel, int32 [event_height, event_width]; the same time rules as ``render``."""
        instant = self.resolve(t_us)
        try:
            events = self.ring.slice(*instant.window)
        except WindowUnavailable as exc:
            self._unavailable(f"the events for t={self._fmt(instant.t_us)} are gone: {exc}")
        emap = accumulate(events, self.meta.event_width, self.meta.event_height)
        return instant, len(events), np.rint(emap).astype(np.int32)

    def default_pose(self, t_us: int) -> np.ndarray:
        """The event camera's own pose at scene time ``t_us`` (the checkpoint's trajectory)."""
        if self.online is not None and int(t_us) > self.end_us:
            # past the span: the pose of the newest online anchor's frame, when the stream gives poses
            for a in reversed(self.online.anchors()):
                if a.t_us <= int(t_us) and a.pose is not None:
                    return a.pose
        if self.meta.trajectory is None:
            raise InvalidInputError("pose is required: this checkpoint has no camera trajectory")
        return self.meta.trajectory.at(int(t_us))

    def intrinsics(self, width: int, height: int) -> Intrinsics:
        native = self.meta.intrinsics
        if (width, height) == (native.width, native.height):
            return native
        return native.scaled(width, height)

    def render(self, t_us: int | None, pose: np.ndarray | None, width: int, height: int, *,
               camera_view: bool | None = None) -> Rendered:
        """Pixels of the scene at ``t_us`` (None: the head) from ``pose`` (None: the event camera's).

        camera_view: whether ``pose`` is the event camera's own at that time (default: when ``pose`` is
        None or equals it, ``CAMERA_POSE_ATOL``). Its view from an online anchor whose frame the stream
        gave is projected onto the events since that frame (``_frame``)."""
        instant = self.resolve(t_us)
        t0 = time.perf_counter()
        state, n_events, emap = self._entry(instant)
        t1 = time.perf_counter()
        c2w = self.default_pose(instant.t_us) if pose is None else pose
        intr = self.intrinsics(width, height)
        image = self.model.render(state, c2w, intr, fast=self.fast, threads=self.raster_threads)
        frame = None if camera_view is False else self._frame(instant)
        if frame is not None and camera_view is None and pose is not None:
            # a pose given is the camera's view when it is the camera's own (checked only where it counts)
            frame = frame if self._is_camera_pose(pose, instant.t_us) else None
        if frame is not None:
            t2 = time.perf_counter()
            shape = (self.meta.event_height, self.meta.event_width)
            image = event_bounds.project(image, frame, np.zeros(shape, np.float32) if emap is None else emap,
                                         self.model.config.contrast_threshold, eps=self.model.config.log_eps)
        pixels = to_uint8(image)  # timed with the last stage, as before the projection
        stages = {"state": t1 - t0, "raster": time.perf_counter() - t1}
        if frame is not None:
            stages["raster"], stages["project"] = t2 - t1, time.perf_counter() - t2
        return Rendered(pixels, instant, n_events, self.anchor_kind(instant), stages, frame is not None)

    def _is_camera_pose(self, pose: np.ndarray, t_us: int) -> bool:
        try:
            own = self.default_pose(t_us)
        except InvalidInputError:  # no trajectory, no frame poses: the camera's pose is unknown
            return False
        return bool(np.allclose(pose, own, rtol=0.0, atol=CAMERA_POSE_ATOL))

    def _frame(self, instant: Instant) -> np.ndarray | None:
        """The frame a render of the event camera's view at ``instant`` is projected onto the events
        since (model/event_bounds.py; the model renders what they leave open): past the span, with
        ``online.project`` on, the stream's frame its window starts at (an online anchor's, or before
        the first one the checkpoint's last anchor's); else None."""
        if self.online is None or not self.online.project or instant.t_us <= self.end_us:
            return None
        return self.online.frame_at(instant.window[0])

    def warm_up(self) -> float:
        """Compile the fast paths (numba) with one render at the first anchor, off the request path.

        Returns the seconds it took.
        """
        t0 = time.perf_counter()
        state = self.model.deform(self.first_us, None)
        c2w = self.default_pose(self.first_us) if self.meta.trajectory is not None else np.eye(4)
        image = self.model.render(state, c2w, self.meta.intrinsics, fast=self.fast,
                                  threads=self.raster_threads)
        one = Events(np.zeros(1, np.int64), np.zeros(1, np.uint16), np.zeros(1, np.uint16),
                     np.ones(1, np.int8))
        emap = accumulate(one, self.meta.event_width, self.meta.event_height)
        if self.meta.has_event_branch and self.end_us > self.first_us:
            self.model.deform(self.first_us + 1, emap)  # past the anchor: at it the branch is skipped
        if self.online is not None:  # the projection's kernel: compiling it holds the GIL for seconds
            event_bounds.project(image, to_uint8(image), emap, self.model.config.contrast_threshold)
        return time.perf_counter() - t0
