"""The render engine: (time, pose, size) -> pixels, from the timebase (the model and where renders start),
the event ring and the stream's frames.

    t ──> stream window [tau, T) on the ring's clock (live/clock.py, pure) ──> events ──> I_E
      ──> the state at tau moved by I_E   (live/timebase.py: the checkpoint's anchor or an online one;
                                           pose-independent: cached, computed once per instant)
      ──> model.render(state, pose, K)    (per client; numba fast path, off the event loop)
      ──> of the event camera's view past the span: projected onto the events since tau's frame
    without a model (a cold start, before the first one is learnt): tau's frame moved by I_E

A newer model comes in whole (``swap``): each render takes the timebase once, so it sees one model
from start to end, and the cache keys on the timebase's serial.

Every method here blocks; the routes call them on the render pool's threads.
"""

from __future__ import annotations

import functools
import time
from dataclasses import dataclass, field

import numpy as np

from edmcgs import protocol
from edmcgs.errors import InvalidInputError, WindowUnavailable
from edmcgs.geometry import Intrinsics
from edmcgs.model.online import bounds as event_bounds
from edmcgs.sensor.buffer.ring import EventRingBuffer
from edmcgs.sensor.event_map import accumulate
from edmcgs.sensor.events import Events
from edmcgs.server.encode import depth_grey, to_uint8
from edmcgs.server.errors import NotReady
from edmcgs.server.live.clock import Instant, Timeline, TimeNotRenderable, fmt
from edmcgs.server.live.playback import Playback
from edmcgs.server.live.timebase import FramesTimebase, Start, Timebase
from edmcgs.server.state_cache import StateCache

CAMERA_POSE_ATOL = 1e-5
"""A pose given whose entries (rotation, translation in m) are all within this of the event camera's
own is its view: at the DAVIS346's focal length (~300 px), a hundredth of a pixel at most."""
NO_POSE = "pose is required: this checkpoint has no camera trajectory"
NO_MODEL = ("no model has been learnt yet: only the event camera's own view renders (no pose, rgb mode) "
            "until the learner publishes one; GET /scene's learning says how far it is")


@dataclass(frozen=True)
class Rendered:
    pixels: np.ndarray  # uint8 [H, W, C]
    instant: Instant
    events: int
    anchor: str = "checkpoint"
    """protocol.ANCHOR_KINDS: the checkpoint's anchor, an online one predicted or corrected, or (no model)
    the stream's frame."""
    stages: dict[str, float] = field(default_factory=dict)
    """Seconds spent per stage: "state" (the events and the deformation, or a cache hit), "raster",
    "project"."""
    projected: bool = False
    """Projected onto the events since the anchor's frame (``Start.frame``)."""
    mode: str = "rgb"
    """What the pixels show (protocol.RENDER_MODES)."""
    depth_range: tuple[float, float] | None = None
    """Depth mode: the (near, far) camera z of grey 255 and 1 (encode.depth_grey); None: no surface in
    view, or another mode."""
    model_version: int | None = 0
    """The model that rendered (``Timebase.version``; None: none yet)."""


class Engine:
    """Owns nothing it did not build: the timebase and ring are passed in (the app's lifespan opens and
    closes them). ``timeline`` is set once the stream's clock is known (at once for a replay, at the
    first event for a camera).

    timebase: the model and where each render starts (live/timebase.py); ring: the event ring the
    ingest thread fills (without a sensor: an empty one); cache_size: deformed states kept;
    raster_threads: threads of the numba rasterizer per render (None: numba's default, all cores);
    playback: without a sensor, the clock that moves the head (live/playback.py).
    """

    def __init__(self, timebase: Timebase | FramesTimebase, ring: EventRingBuffer, *, cache_size: int = 32,
                 raster_threads: int | None = None, playback: Playback | None = None):
        self.ring = ring
        self.timebase = timebase
        self.playback = playback
        self.timeline: Timeline | None = None if playback is None else playback.timeline
        self.cache = StateCache(cache_size)
        self.raster_threads = raster_threads

    def swap(self, timebase: Timebase) -> None:
        """Serve ``timebase`` (a newer model) from the next render on; renders running finish on theirs."""
        self.timebase = timebase

    @property
    def model(self):
        """The model rendered now (None: none learnt yet)."""
        return self.timebase.model

    @property
    def meta(self):
        return self.timebase.meta

    @property
    def first_us(self) -> int:
        """The first renderable scene time (the Markov chain has no state before it)."""
        return self.timebase.extent(None)[0]

    @property
    def end_us(self) -> int:
        """The last scene time a sweep runs to by default: the span's end, or the head past it."""
        head = self.head()
        return self.timebase.extent(None if head is None else head[1])[1]

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

    def resolve(self, t_us: int | None, timebase=None) -> Instant:
        """The instant rendered for scene time ``t_us`` (None: the head), or TimeNotRenderable."""
        tb = timebase or self.timebase
        head = self.head()
        if head is None:
            raise TimeNotRenderable("no events have arrived yet; retry in a moment", None)
        try:
            return tb.resolve(t_us, head, self.timeline)
        except TimeNotRenderable as exc:
            self._unavailable(str(exc), tb)

    def tau_ranges(self) -> list[dict]:
        """GET /scene's ``tau_sources``: where tau comes from, by range of scene time (protocol.py)."""
        head = self.head()
        return [{"source": source.value, **self.range_dict((lo, hi))}
                for source, lo, hi in self.timebase.tau_ranges(None if head is None else head[1])]

    # ------------------------------------------------------------------ what can be rendered
    def renderable(self, timebase=None) -> list[tuple[int, int]]:
        """Scene-time intervals [lo, hi] (µs, inclusive) that can be rendered now, oldest first."""
        head = self.head()
        if head is None:
            return []
        return (timebase or self.timebase).renderable(head, self.timeline, self.ring.stats())

    def valid_range(self) -> dict | None:
        """The protocol's ``valid_range``: the most recent renderable interval."""
        ranges = self.renderable()
        return self.range_dict(ranges[-1]) if ranges else None

    def range_dict(self, interval: tuple[int, int]) -> dict:
        lo, hi = interval
        return {"t_min": self.seconds_of(lo), "t_max": self.seconds_of(hi), "t_us_min": lo, "t_us_max": hi}

    def _unavailable(self, message: str, timebase=None):
        ranges = self.renderable(timebase)
        if ranges:
            listed = ", ".join(f"[{self.seconds_of(a):.6f}, {self.seconds_of(b):.6f}] s "
                               f"(t_us [{a}, {b}])" for a, b in ranges)
            message += f"; renderable now: {listed}"
        else:
            message += "; nothing is renderable yet"
        raise TimeNotRenderable(message, self.range_dict(ranges[-1]) if ranges else None)

    def _fmt(self, t_us: int) -> str:
        return fmt(t_us, self.meta.t_start_us)

    # ------------------------------------------------------------------ deformation and render
    def state(self, instant: Instant) -> tuple[object, int]:
        """(GaussianState at the instant, events in its window), shared by all clients (cached)."""
        tb = self.timebase
        if tb.model is None:
            raise NotReady(NO_MODEL)
        _, state, n_events, _ = self._entry(tb, instant, lambda: tb.pose(instant.t_us))
        return state, n_events

    def anchor_kind(self, instant: Instant) -> str:
        """protocol.ANCHOR_KINDS of the instant's anchor."""
        return self.timebase.start(instant).kind

    def _entry(self, tb, instant: Instant, pose) -> tuple[Start, object, int, np.ndarray | None]:
        """(its start, the state (None without a model), events in its window, the window's I_E (None: no
        events, or none needed)); the last three cached. pose: () -> the event camera's pose (or None)."""
        start = tb.start(instant)
        key = (tb.serial, instant.t_us, instant.anchor_us, instant.window, start.version)
        return start, *self.cache.get(key, lambda: self._deform(tb, instant, start, pose))

    def _deform(self, tb, instant: Instant, start: Start, pose) -> tuple[object, int, np.ndarray | None]:
        events = self._events(instant, tb)
        emap = None  # the model's input, and what a render is projected onto (Start.frame)
        meta = tb.meta
        if (meta.has_event_branch or start.frame is not None) and len(events):
            emap = accumulate(events, meta.event_width, meta.event_height)
        state = None if tb.model is None else tb.state(start, instant, emap, pose())
        return state, len(events), emap

    def _events(self, instant: Instant, timebase=None) -> Events:
        try:
            return self.ring.slice(*instant.window)
        except WindowUnavailable as exc:
            self._unavailable(f"the events for t={self._fmt(instant.t_us)} are gone: {exc}", timebase)

    def event_map(self, t_us: int | None) -> tuple[Instant, int, np.ndarray]:
        """(instant, events, I_E) of the window a render at ``t_us`` (None: the head) uses: the signed
        polarity sum per pixel, int32 [event_height, event_width]; the same time rules as ``render``."""
        tb = self.timebase
        instant = self.resolve(t_us, tb)
        events = self._events(instant, tb)
        emap = accumulate(events, tb.meta.event_width, tb.meta.event_height)
        return instant, len(events), np.rint(emap).astype(np.int32)

    def default_pose(self, t_us: int) -> np.ndarray:
        """The event camera's own pose at scene time ``t_us`` (InvalidInputError when unknown)."""
        pose = self.timebase.pose(t_us)
        if pose is None:
            raise InvalidInputError(NO_POSE)
        return pose

    def intrinsics(self, width: int, height: int, meta=None) -> Intrinsics:
        native = (meta or self.meta).intrinsics
        if (width, height) == (native.width, native.height):
            return native
        return native.scaled(width, height)

    def render(self, t_us: int | None, pose: np.ndarray | None, width: int, height: int, *,
               camera_view: bool | None = None, mode: str = "rgb") -> Rendered:
        """Pixels of the scene at ``t_us`` (None: the head) from ``pose`` (None: the event camera's).

        camera_view: whether ``pose`` is the event camera's own at that time (default: when ``pose`` is
        None or equals it, ``CAMERA_POSE_ATOL``). Its view from an anchor whose frame the stream gave
        (past the span) is projected onto the events since that frame (``Start.frame``); without a model
        it is that frame moved by them, and nothing else renders.
        mode: protocol.RENDER_MODES; depth and alpha are grey [H, W, 1] (encode.depth_grey, to_uint8),
        the splats' alone, never projected."""
        if mode not in protocol.RENDER_MODES:
            raise InvalidInputError(f"mode must be one of {', '.join(protocol.RENDER_MODES)}, got {mode!r}")
        tb = self.timebase  # one model for the whole render, whatever a swap does meanwhile
        instant = self.resolve(t_us, tb)
        own = functools.cache(lambda: tb.pose(instant.t_us))  # looked up once, where needed
        t0 = time.perf_counter()
        start, state, n_events, emap = self._entry(tb, instant, own)
        t1 = time.perf_counter()
        meta = tb.meta
        if tb.model is None:
            if (pose is not None and camera_view is not True) or mode != "rgb":
                raise NotReady(NO_MODEL)
        # the event camera's view where no model can draw it (none yet, or a moving camera past the poses
        # it learnt): the frame at tau moved by the events since
        if tb.model is None or (pose is None and mode == "rgb" and start.frame is not None
                                and not tb.pose_known(instant.t_us)):
            sensor = meta if tb.model is None else tb.model.config  # C and eps of the integration
            moved = np.zeros((meta.event_height, meta.event_width), np.float32) if emap is None else emap
            image = event_bounds.integrate(start.frame, moved, sensor.contrast_threshold,
                                           size=(width, height), eps=sensor.log_eps)
            return Rendered(to_uint8(image), instant, n_events, "frame",
                            {"state": t1 - t0, "project": time.perf_counter() - t1}, True, model_version=None)
        c2w = own() if pose is None else pose
        if c2w is None:
            raise InvalidInputError(NO_POSE)
        intr = self.intrinsics(width, height, meta)
        model = tb.model
        fast = model.center.device.type == "cpu"  # numba on a CPU; the torch rasterizer on a GPU
        if mode != "rgb":
            depth, alpha = model.render_depth_alpha(state, c2w, intr, fast=fast, threads=self.raster_threads)
            depth_range = None
            if mode == "depth":
                pixels, near, far = depth_grey(depth, alpha)
                depth_range = None if near is None else (near, far)
            else:
                pixels = to_uint8(alpha[..., None])
            stages = {"state": t1 - t0, "raster": time.perf_counter() - t1}
            return Rendered(pixels, instant, n_events, start.kind, stages, mode=mode, depth_range=depth_range,
                            model_version=tb.version)
        image = model.render(state, c2w, intr, fast=fast, threads=self.raster_threads)
        if camera_view is None:  # a pose given is the camera's view when it is its own (checked where it can)
            camera_view = pose is None or (start.frame is not None and own() is not None
                                           and np.allclose(pose, own(), rtol=0.0, atol=CAMERA_POSE_ATOL))
        frame = start.frame if camera_view else None
        if frame is not None:
            t2 = time.perf_counter()
            shape = (meta.event_height, meta.event_width)
            image = event_bounds.project(image, frame, np.zeros(shape, np.float32) if emap is None else emap,
                                         model.config.contrast_threshold, eps=model.config.log_eps)
        pixels = to_uint8(image)  # timed with the last stage, as before the projection
        stages = {"state": t1 - t0, "raster": time.perf_counter() - t1}
        if frame is not None:
            stages["raster"], stages["project"] = t2 - t1, time.perf_counter() - t2
        return Rendered(pixels, instant, n_events, start.kind, stages, frame is not None,
                        model_version=tb.version)

    def warm_up(self, timebase=None) -> float:
        """Compile the fast paths (numba) with one render at the first anchor, off the request path (of
        ``timebase``, default the current one). Returns the seconds it took."""
        tb = timebase or self.timebase
        t0 = time.perf_counter()
        meta, model = tb.meta, tb.model
        one = Events(np.zeros(1, np.int64), np.zeros(1, np.uint16), np.zeros(1, np.uint16),
                     np.ones(1, np.int8))
        emap = accumulate(one, meta.event_width, meta.event_height)
        if model is None:  # the integration's kernel (it is what renders until a model arrives)
            frame = np.zeros((meta.intrinsics.height, meta.intrinsics.width, meta.channels), np.uint8)
            event_bounds.integrate(frame, emap, meta.contrast_threshold)
            return time.perf_counter() - t0
        first = tb.span.first_us
        fast = model.center.device.type == "cpu"
        state = model.deform(first, None)
        c2w = tb.pose(first)
        image = model.render(state, np.eye(4) if c2w is None else c2w, meta.intrinsics, fast=fast,
                             threads=self.raster_threads)
        if meta.has_event_branch and tb.span.end_us > first:
            model.deform(first + 1, emap)  # past the anchor: at it the branch is skipped
        if tb.online is not None:  # the projection's kernel: compiling it holds the GIL for seconds
            event_bounds.project(image, to_uint8(image), emap, model.config.contrast_threshold)
        return time.perf_counter() - t0
