"""The engine's one seam to the live path: where every render starts, and the model it renders.

For a scene time t a timebase decides tau(t) and says what stands at tau (a ``Start``):

- ``Timebase``, a checkpoint's: by ``clock.TauRule``, within the span its own anchors (``EdMCGS.tau``),
  past it the online anchors. At tau stands the checkpoint's anchor, from which the model deforms by the
  events since it, or an online anchor, whose state the transition moves by them.
- ``FramesTimebase``, before any model (a cold start, ``server/live/learning.py``): tau is the stream's
  newest frame, and the event camera's view is that frame moved by the events since it
  (``model/online/bounds.integrate``), the best render without a model.

A timebase also knows the event camera's pose at t and what is renderable up to the head. The engine
(engine.py) composes it with the ring, the cache and the rasterizer, takes it once per render, and is
handed a new one whole when a newer model arrives (``Engine.swap``).
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np

from edmcgs.errors import WindowUnavailable
from edmcgs.geometry import Intrinsics
from edmcgs.luminance import LOG_EPS
from edmcgs.model.dynamic import EdMCGS, SceneMeta
from edmcgs.model.motion.gaussians import GaussianState
from edmcgs.model.online import state_of, with_spawned
from edmcgs.protocol import TauSource
from edmcgs.sensor.buffer.anchors import AnchorStore
from edmcgs.sensor.buffer.ring import RingStats
from edmcgs.server.live import clock
from edmcgs.server.live.anchors import OnlineAnchor, OnlineAnchors
from edmcgs.server.live.clock import Instant, Span, Timeline, TimeNotRenderable


@dataclass(frozen=True)
class Start:
    """What stands at a render's anchor tau(t)."""

    kind: str
    """protocol.ANCHOR_KINDS: the checkpoint's anchor, or an online one predicted or corrected."""
    version: tuple[int, int] | None
    """Changes whenever the state at tau does (part of the deform cache's key); None: it never does."""
    online: OnlineAnchor | None = None
    """The online anchor (None: the checkpoint's)."""
    frame: np.ndarray | None = None
    """The stream's frame at tau, when renders of the event camera's view are projected onto the events
    since it (past the span, ``OnlineConfig.project``), or moved by them (no model); else None."""


CHECKPOINT = Start("checkpoint", None)
_SERIALS = itertools.count()


def _stream_tau(frames: AnchorStore, stream_t: int) -> int | None:
    try:
        return frames.tau(stream_t)
    except WindowUnavailable as exc:  # evicted
        raise TimeNotRenderable(str(exc)) from None


class Timebase:
    """model: the served checkpoint; online: its online anchors past the span (None: the span's end is
    the last renderable time); frames: the stream's frames where the service keeps them (a cold start,
    whose model learnt them): renders of the event camera's view within the span are then projected onto
    the one at their anchor, as they are past it."""

    def __init__(self, model: EdMCGS, online: OnlineAnchors | None = None,
                 frames: AnchorStore | None = None, *, version: int = 0):
        self.model, self.online, self.frames = model, online, frames
        self.version = version
        """The model's: 0 a checkpoint given, n the n-th a cold start learnt (protocol.FrameMeta)."""
        self.meta: SceneMeta = model.meta
        self.serial = next(_SERIALS)
        """Told apart from every other timebase of the process (the engine's cache keys on it)."""
        meta = model.meta
        self.origin_us = int(meta.t_start_us)
        self.scene_anchors = np.asarray(meta.anchors_us, dtype=np.int64)
        self.span = Span(int(self.scene_anchors[0]), int(meta.t_end_us))
        self.rule = clock.TauRule(self.span, stream_frames=online is not None, online=online is not None)

    # ------------------------------------------------------------------ time
    def resolve(self, t_us: int | None, head: tuple[int, int], timeline: Timeline) -> Instant:
        """The instant rendered for scene time ``t_us`` (None: the head), given the head (stream µs, scene
        µs); TimeNotRenderable says why not."""
        end = self.rule.end(head[1]) if self.online is not None else None
        query = clock.locate(t_us, head[0], timeline, self.span, self.origin_us, end)
        return clock.instant(query, self.tau(query.stream_t, query.t_us), timeline, self.span, self.origin_us)

    def tau(self, stream_t: int, scene_t: int) -> int | None:
        """tau on the stream clock for the time ``stream_t`` (scene ``scene_t``), from where the rule
        says; None where no anchor precedes it."""
        source = self.rule.source(scene_t)
        if source is TauSource.CHECKPOINT:
            return stream_t - (scene_t - self.model.tau(scene_t))
        if source is TauSource.ONLINE:
            return self.online.tau(stream_t, scene_t)
        return None

    def extent(self, head_scene_us: int | None) -> tuple[int, int]:
        """The first and last scene µs a render may ask for (a sweep's default ends)."""
        return self.span.first_us, self.rule.end(head_scene_us)

    def tau_ranges(self, head_scene_us: int | None) -> list[tuple[TauSource, int, int]]:
        """GET /scene's ``tau_sources``: (source, first µs, last µs inclusive) in order."""
        return self.rule.ranges(head_scene_us)

    def renderable(self, head: tuple[int, int], timeline: Timeline,
                   stats: RingStats) -> list[tuple[int, int]]:
        """Scene-time intervals [lo, hi] (µs, inclusive) renderable now, oldest first, given the head
        (stream µs, scene µs) and what the ring holds."""
        dropped = bool(stats.overflowed or stats.expired)
        ranges = clock.renderable(head[0], timeline, self.span, self.scene_anchors, stats.oldest_us, dropped)
        if self.online is None or head[1] <= self.span.end_us:
            return ranges
        # Past the span, up to the head: from the checkpoint's last anchor of this pass, or from the
        # oldest online anchor whose events the ring still holds.
        floor = (stats.oldest_us + 1 if stats.oldest_us is not None else None) if dropped else None
        last_ckpt_stream = head[0] - (head[1] - int(self.scene_anchors[-1]))
        if floor is None or last_ckpt_stream >= floor:
            lo = self.span.end_us + 1
        else:
            lo = next((a.t_us for a in self.online.anchors()
                       if a.stream_us >= floor and a.stream_us > last_ckpt_stream), None)
            if lo is None:
                return ranges
        if ranges and ranges[-1][1] + 1 >= lo:
            return [*ranges[:-1], (ranges[-1][0], head[1])]
        return [*ranges, (lo, head[1])]

    # ------------------------------------------------------------------ what stands at tau
    def start(self, instant: Instant) -> Start:
        """What the render at ``instant`` starts from (cheap: a lookup, no computation)."""
        online, tau = self.online, instant.window[0]
        past = online is not None and instant.t_us > self.span.end_us
        anchor = online.get(tau) if past else None
        frame = None
        if online is None or online.config.project:
            frame = anchor.frame if anchor is not None else self._frame(tau, past)
        if anchor is None:  # within the span, or past it before the first online anchor
            return CHECKPOINT if frame is None else Start("checkpoint", None, None, frame)
        return Start("corrected" if anchor.corrected else "predicted",
                     (anchor.version, online.transitions.version), anchor, frame)

    def _frame(self, tau_stream: int, past: bool) -> np.ndarray | None:
        """The stream's frame at ``tau_stream`` (the checkpoint's anchor), where it is kept: in ``frames``,
        or past the span the one online anchors took at the span's last anchor; else None."""
        if self.frames is not None:
            try:
                kept = self.frames.anchor_at(tau_stream)
            except WindowUnavailable:
                kept = None
            if kept is not None and kept.t_us == tau_stream:
                return kept.image
        return self.online.frame_at(tau_stream) if past else None

    def state(self, start: Start, instant: Instant, event_map: np.ndarray | None,
              pose: np.ndarray | None) -> GaussianState:
        """The Gaussians at ``instant``: the state at its start moved by ``event_map`` (I_E of its window;
        None: no events), seen by the event camera from ``pose`` (None: unknown)."""
        if start.online is None:
            return self.model.deform(instant.t_us, event_map, anchor_us=instant.anchor_us)
        online = self.online
        motion = online.advance(start.online.motion, event_map, pose)
        return with_spawned(state_of(self.model, motion, start.online.colors), start.online.spawned)

    def pose_known(self, t_us: int) -> bool:
        """Whether ``pose(t_us)`` is where the event camera is, for a cold start's model (``frames``
        kept): within the span, past it from the model's last anchor, and from an online anchor whose
        frame came with a pose or when the camera stood still. A moving camera at an online anchor with no
        pose is somewhere the learnt trajectory's clamped end does not say: its view is then the frame
        moved by the events (``Engine.render``), not the model from a stale pose. (A checkpoint given
        keeps its trajectory's clamped end past its span.)"""
        if self.online is None or self.frames is None or int(t_us) <= self.span.end_us:
            return True
        newest = next((a for a in reversed(self.online.anchors()) if a.t_us <= int(t_us)), None)
        if newest is None or newest.pose is not None:
            return True
        trajectory = self.meta.trajectory
        return trajectory is None or trajectory.is_static

    def pose(self, t_us: int) -> np.ndarray | None:
        """The event camera's pose at scene time ``t_us``: past the span the newest online anchor's frame's
        when the stream gives poses, else the checkpoint's trajectory; None when neither knows it."""
        if self.online is not None and int(t_us) > self.span.end_us:
            for a in reversed(self.online.anchors()):
                if a.t_us <= int(t_us) and a.pose is not None:
                    return a.pose
        trajectory = self.model.meta.trajectory
        return None if trajectory is None else trajectory.at(int(t_us))


@dataclass(frozen=True)
class StreamMeta:
    """What a scene without a model knows of itself (what the engine reads of a ``SceneMeta``): the
    stream's camera, from its first frame on."""

    t_start_us: int
    """The first frame's time: the scene's origin, as the model learnt from the stream will have it."""
    intrinsics: Intrinsics
    """The frames' camera (given, or assumed: ``pipeline.recording_intrinsics``)."""
    event_width: int
    event_height: int
    channels: int
    """Of the frames: 1 (grey) or 3 (RGB)."""
    contrast_threshold: float
    """C of the integration: the recording's when it states one."""
    log_eps: float = LOG_EPS
    trajectory = None
    has_event_branch = False


class FramesTimebase:
    """Before any model: tau(t) is the stream's newest frame at or before t (``frames``, filled by the
    ingest thread), and the event camera's view at t is that frame moved by the events since it."""

    model = None
    online = None
    version = None

    def __init__(self, meta: StreamMeta, frames: AnchorStore):
        self.meta, self.frames = meta, frames
        self.origin_us = int(meta.t_start_us)
        self.serial = next(_SERIALS)

    def resolve(self, t_us: int | None, head: tuple[int, int], timeline: Timeline) -> Instant:
        span = Span(self.origin_us, max(self.origin_us, head[1]))
        query = clock.locate(t_us, head[0], timeline, span, self.origin_us, head[1])
        return clock.instant(query, _stream_tau(self.frames, query.stream_t), timeline, span, self.origin_us)

    def tau_ranges(self, head_scene_us: int | None) -> list[tuple[TauSource, int, int]]:
        if head_scene_us is None or head_scene_us < self.origin_us:
            return []
        return [(TauSource.STREAM, self.origin_us, int(head_scene_us))]

    def extent(self, head_scene_us: int | None) -> tuple[int, int]:
        return self.origin_us, max(self.origin_us, int(head_scene_us or self.origin_us))

    def renderable(self, head: tuple[int, int], timeline: Timeline,
                   stats: RingStats) -> list[tuple[int, int]]:
        """From the oldest retained frame whose events since are all in the ring, to the head."""
        times = self.frames.times()
        if stats.overflowed or stats.expired:
            times = times[times > (stats.oldest_us if stats.oldest_us is not None else head[0])]
        times = times[times <= head[0]]
        return [] if not len(times) else [(timeline.scene_of(int(times[0])), head[1])]

    def start(self, instant: Instant) -> Start:
        return Start("frame", None, None, self.frames.anchor_at(instant.window[0]).image)

    def pose(self, t_us: int) -> np.ndarray | None:
        return None  # nothing knows the camera's motion before a model (or poses) does

    def pose_known(self, t_us: int) -> bool:
        return False
