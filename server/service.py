"""One running service: the model, the event source and its ingest thread, the ring, the engine, the
render pool and the metrics. Opened and closed by the app's lifespan (``app.py``).

A checkpoint without an event branch may be served alone (no --replay, no --live): no source, no
ingest thread, an empty one-slot ring, tau(t) from the checkpoint's anchors, the whole span renderable
at once, and a playback clock looping over the span at ``speed`` as the head that GET /render without
t and the websocket's live mode follow (live/playback.py). A checkpoint with an event branch needs its
events: alone it is refused, naming the fix.

With a sensor, tau(t) comes from the checkpoint's anchors over its span (live/clock.TauRule); past its end
a source's frames become online anchors (live/anchors.py: predicted by the event transition, corrected in
the background), so a stream longer than the span renders to its head.

A source without a checkpoint is a cold start (live/learning.py): the stream's frames moved by the events
since each render at once, and a learner beside the server trains a model on them; each model it
publishes is built into a timebase here, off the render path, and swapped into the engine whole.
"""

from __future__ import annotations

import asyncio
import logging
import os
import threading
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from edmcgs import protocol
from edmcgs.errors import EdmcgsError, InvalidInputError, RenderError
from edmcgs.geometry import Intrinsics
from edmcgs.model.checkpoint import load_checkpoint
from edmcgs.model.config import preset
from edmcgs.model.eval.baselines import DEFAULT_CONTRAST
from edmcgs.model.render import rasterize_fast
from edmcgs.model.render.jit import compiled
from edmcgs.pipeline import parse_intrinsics
from edmcgs.sensor.buffer.anchors import AnchorStore
from edmcgs.sensor.buffer.ingest import Ingest
from edmcgs.sensor.buffer.ring import EventRingBuffer
from edmcgs.sensor.frames import Frames
from edmcgs.sensor.sources.base import EventSource, SensorBatch
from edmcgs.sensor.sources.open import open_source
from edmcgs.sensor.sources.pacing import Pacing
from edmcgs.server import demo
from edmcgs.server.encode import encode, event_rgba
from edmcgs.server.engine import Engine
from edmcgs.server.live.anchors import OnlineAnchors
from edmcgs.server.live.anchors import register_metrics as register_online_metrics
from edmcgs.server.live.clock import Timeline
from edmcgs.server.live.config import LearnConfig
from edmcgs.server.live.learning import Learning
from edmcgs.server.live.playback import Playback
from edmcgs.server.live.signal import Arrivals, HeadSignal
from edmcgs.server.live.timebase import FramesTimebase, StreamMeta, Timebase
from edmcgs.server.metrics import Metrics
from edmcgs.server.render_pool import RenderPool
from edmcgs.server.settings import Settings
from edmcgs.server.views import training_views

log = logging.getLogger("edmcgs.server")

def _warm_up(engine: Engine) -> float:
    """``engine.warm_up()``, announced first where the renderer's kernels are not in numba's cache yet
    (the start would otherwise look hung)."""
    model = engine.model
    if model is not None and model.center.device.type == "cpu" and not compiled(*rasterize_fast.KERNELS):
        log.info("compiling the renderer's kernels (first run only, about %d s; edmcgs warm-up does it "
                 "ahead) ...", rasterize_fast.COMPILE_S)
    return engine.warm_up()


def invalid(param: str, message: str) -> InvalidInputError:
    """An InvalidInputError that names the offending request parameter (mapped to 422)."""
    exc = InvalidInputError(message)
    exc.param = param
    return exc


@dataclass(frozen=True)
class Inputs:
    """What to serve, resolved from the settings."""

    checkpoint: Path | None
    """None with a source: learn the model while serving (a cold start)."""
    replay: Path | None
    live: bool
    loop: bool

    @property
    def sensorless(self) -> bool:
        return self.replay is None and not self.live


def resolve_inputs(settings: Settings) -> Inputs:
    """The checkpoint and source to open: the given ones, or the bundled demo's."""
    if settings.uses_demo:
        ckpt, rec = demo.files()
        return Inputs(ckpt, rec, live=False, loop=True)
    return Inputs(settings.checkpoint, settings.replay, settings.live, settings.loop)


@dataclass(frozen=True)
class RenderedFrame:
    """One render as the routes send it: the wire's description, the encoded bytes, and the event window
    it used (the half-open [tau, T) on the ring's clock; the stream route needs it, the wire does not)."""

    meta: protocol.FrameMeta
    data: bytes
    window: tuple[int, int]


def learn_config(settings: Settings, info, extras) -> LearnConfig:
    """How a cold start's learner trains on a stream (``info``, ``extras``: what its source states), the
    settings' names checked now rather than in the learner."""
    if settings.intrinsics is not None:
        intrinsics = tuple(float(v) for v in parse_intrinsics(settings.intrinsics, info.width, info.height))
    elif extras.intrinsics is not None:
        intrinsics = tuple(extras.intrinsics)
    else:
        intrinsics = None
        log.warning("no intrinsics given or stated: the learner estimates them with the camera's poses if "
                    "it moves, else assumes fx = fy = width, centred (--intrinsics)")
    config = LearnConfig(workdir=settings.learn_dir, intrinsics=intrinsics,
                         contrast_threshold=extras.contrast_threshold, preset=settings.learn_preset,
                         overrides=tuple(settings.learn_set), poses=settings.learn_poses,
                         trajectory=None if extras.trajectory_t_us is None else
                         (extras.trajectory_t_us, extras.trajectory_c2w),
                         anchor_fps=settings.learn_anchor_fps, first_steps=settings.learn_first_steps,
                         publish_s=settings.learn_publish_s)
    for each in config.presets():
        preset(each).with_overrides(settings.learn_set)
    return config


def beside_learner(learner_threads: int) -> int:
    """Raster threads of a render while a learner runs on ``learner_threads`` cores: the cores left. A
    render's threads on the learner's core wait on it, and numba's spin after each render, so more
    threads cost (street3d on 2 cores, the learner on one: render 9.2 ms on two threads, 5.5 on one;
    the deformation before it 8.3 ms against 4.6)."""
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1
    return max(1, cores - learner_threads)


class Service:
    """Built by ``open`` (blocking: loads, opens, warms up, starts ingesting); ``close`` undoes it."""

    def __init__(self, settings: Settings, inputs: Inputs, source: EventSource | None,
                 ring: EventRingBuffer, engine: Engine, frames: AnchorStore | None = None,
                 learning: Learning | None = None):
        self.settings, self.inputs = settings, inputs
        self.source, self.ring, self.engine, self.frames = source, ring, engine, frames
        self.learning = learning
        """A cold start's learner (None: the checkpoint is given); each model it publishes comes here."""
        if learning is not None:
            learning.on_model = self._take_model
        self._swap = threading.Lock()  # the ingest thread's frames and a model swap, one at a time
        self._origin_set = False
        self.metrics = Metrics()
        self.arrivals = Arrivals()
        self.pool = RenderPool(settings.render_workers, settings.render_queue, settings.stream_workers)
        self.signal: HeadSignal | None = None
        self.ingest: Ingest | None = None
        self.started_unix = time.time()
        self._register_metrics()

    # ------------------------------------------------------------------ lifecycle
    @classmethod
    def open(cls, settings: Settings, source: EventSource | None = None, learning=None) -> Service:
        """``source``: an already open one to serve instead of the settings' (a camera shared by several
        processes is read through one); closed with the service. ``learning``: a cold start's learner
        as ``Learning(config, width, height)`` builds one (default: its own process; a scene on Ray
        takes its scene's shared learner)."""
        inputs = resolve_inputs(settings)
        if settings.torch_threads is not None:
            import torch

            torch.set_num_threads(settings.torch_threads)
        if inputs.checkpoint is None:
            return cls._open_learning(settings, inputs, source, learning)
        model = load_checkpoint(inputs.checkpoint, settings.device)
        if inputs.sensorless:
            return cls._open_sensorless(settings, inputs, model)
        meta = model.meta
        pacing = Pacing(factor=settings.speed, loop=inputs.loop, batch_us=settings.replay_batch_us)
        if source is None:
            source = open_source(inputs.replay, live=inputs.live, pacing=pacing)
        try:
            info = source.info
            if (info.width, info.height) != (meta.event_width, meta.event_height):
                raise InvalidInputError(
                    f"the event source is {info.width}x{info.height} but the checkpoint's event maps are "
                    f"{meta.event_width}x{meta.event_height}: replay the recording it was trained on")
            ring = EventRingBuffer(settings.ring_events)
            # Past the span, the stream's frames become online anchors (live/anchors.py).
            online = OnlineAnchors(model, ring, settings.online) if info.has_frames else None
            engine = Engine(Timebase(model, online), ring, cache_size=settings.deform_cache,
                            raster_threads=settings.raster_threads)
            if info.t_range_us is not None:
                engine.timeline = replay_timeline(info.t_range_us, meta.t_start_us, meta.t_end_us,
                                                  inputs.loop)
                retain_passes(ring, engine.timeline)
            service = cls(settings, inputs, source, ring, engine)
            seconds = _warm_up(engine)
            log.info("model %s on %s: %d Gaussians, warm-up %.1f s; source %s (%dx%d, %s)",
                     inputs.checkpoint, settings.device, len(model.gaussians), seconds, info.sensor,
                     info.width, info.height, "tau from the checkpoint's anchors" + (
                         ", online anchors from its frames past the span" if online is not None else ""))
            return service
        except BaseException:
            source.close()
            raise

    @classmethod
    def _open_sensorless(cls, settings: Settings, inputs: Inputs, model) -> Service:
        """A checkpoint without an event branch, served alone (see the module docstring)."""
        meta = model.meta
        if meta.has_event_branch:
            raise InvalidInputError(
                f"the checkpoint {str(inputs.checkpoint)!r} has an event branch: it renders from the events "
                "since each anchor, so it needs an event source. Give --replay REC (the recording it was "
                "trained on) or --live; only a checkpoint trained without events (events=false, or a "
                "recording without events) is served without a sensor")
        ring = EventRingBuffer(1)  # never written: there are no events
        playback = Playback(int(meta.anchors_us[0]), meta.t_end_us, settings.speed)
        engine = Engine(Timebase(model), ring, cache_size=settings.deform_cache,
                        raster_threads=settings.raster_threads, playback=playback)
        service = cls(settings, inputs, None, ring, engine)
        seconds = _warm_up(engine)
        log.info("model %s on %s: %d Gaussians, warm-up %.1f s; no sensor (no event branch): the span "
                 "plays in a loop at %gx", inputs.checkpoint, settings.device, len(model.gaussians), seconds,
                 settings.speed)
        return service

    @classmethod
    def _open_learning(cls, settings: Settings, inputs: Inputs, source: EventSource | None,
                       learning=None) -> Service:
        """A source without a checkpoint: serve its frames moved by the events at once, and learn."""
        pacing = Pacing(factor=settings.speed, loop=inputs.loop, batch_us=settings.replay_batch_us)
        if inputs.loop:
            raise InvalidInputError("a cold start learns one pass of the stream: --loop needs a checkpoint")
        if source is None:
            source = open_source(inputs.replay, live=inputs.live, pacing=pacing)
        try:
            info, extras = source.info, source.extras
            name = "the camera" if info.live else str(inputs.replay)
            if not info.has_frames:
                raise InvalidInputError(f"{name} has no frames: a cold start learns the scene from its "
                                        "frames and events; give --checkpoint to serve a model trained "
                                        "beforehand")
            if info.frame_size is not None and info.frame_size != (info.width, info.height):
                raise InvalidInputError(f"{name}'s frames are {info.frame_size[0]}x{info.frame_size[1]}, "
                                        f"its events {info.width}x{info.height}: a cold start needs one "
                                        "resolution")
            config = learn_config(settings, info, extras)
            intrinsics = config.intrinsics
            if intrinsics is None:  # the learner estimates them; renders before it do with this
                w, h = info.width, info.height
                intrinsics = (float(w), float(w), (w - 1) / 2, (h - 1) / 2)
            contrast = extras.contrast_threshold or DEFAULT_CONTRAST
            ring = EventRingBuffer(settings.ring_events)
            frames = AnchorStore(settings.frames_kept)
            origin = info.t_range_us[0] if info.t_range_us is not None else 0  # set by the first frame
            meta = StreamMeta(origin, Intrinsics(*intrinsics, info.width, info.height), info.width,
                              info.height, 1, contrast)
            engine = Engine(FramesTimebase(meta, frames), ring, cache_size=settings.deform_cache,
                            raster_threads=settings.raster_threads or beside_learner(config.threads))
            service = cls(settings, inputs, source, ring, engine, frames,
                          (learning or Learning)(config, info.width, info.height))
            seconds = _warm_up(engine)
            log.info("cold start on %s: learning from %s (%dx%d) into %s, warm-up %.1f s; until the first "
                     "model, renders are the newest frame moved by the events since", settings.device,
                     info.sensor, info.width, info.height, config.workdir, seconds)
            return service
        except BaseException:
            source.close()
            raise

    def _take_model(self, model, report: dict) -> None:
        """The learner's thread: build a newly learnt model's timebase (its online anchors seeded with the
        stream's frames past its span), warm it up, and swap it in."""
        online = OnlineAnchors(model, self.ring, self.settings.online)
        tb = Timebase(model, online, self.frames, version=report["version"])
        self.engine.warm_up(tb)
        seeded = self._seed(online, model.meta.t_end_us)
        with self._swap:  # every frame of the stream reaches the online anchors of one timebase or the other
            self._seed(online, seeded)
            online.on_fit = self._on_fit
            online.start()
            old = self.engine.timebase
            self.engine.swap(tb)
        if self.signal is not None:  # live streams render the head again, with the new model
            self.signal.notify()
        if old.online is not None:
            old.online.stop()

    def _seed(self, online: OnlineAnchors, after_us: int) -> int:
        """Give ``online`` the stream's newest frames after ``after_us`` (as many as it keeps: the chain
        past a model learnt far behind the head starts again at the first, ``OnlineAnchors._predict``);
        returns the newest time given."""
        times = self.frames.times()
        newest = int(times[-1]) if len(times) else after_us
        picked = [self.frames.anchor_at(int(t)) for t in times[times > after_us][-online.config.capacity:]]
        if picked and self.engine.timeline is not None:
            online.on_frames(Frames(np.array([a.t_us for a in picked], np.int64),
                                    np.stack([a.image for a in picked])), self.engine.timeline.scene_of)
        return max(newest, after_us)

    def _on_fit(self, seconds: float, before: float, after: float) -> None:
        self.metrics.fit.observe(seconds)
        self.metrics.fit_loss.observe(after)

    def start(self, loop: asyncio.AbstractEventLoop) -> None:
        """Start ingesting (the replay's real-time clock starts here) and waking live streams on ``loop``."""
        self.signal = HeadSignal(loop)
        if self.online is not None:
            self.online.on_fit = self._on_fit
            self.online.start()
        if self.learning is not None:
            self.learning.start()
        if self.source is not None:
            self.ingest = Ingest(self.source, self.ring, self.frames, on_batch=self._on_batch).start()

    def close(self) -> None:
        """Stop the ingest thread (joined), close the source, finish running renders."""
        if self.ingest is not None:
            self.ingest.stop(timeout=5.0)
            if self.ingest.running:
                log.warning("the ingest thread did not stop within 5 s")
        if self.source is not None:
            self.source.close()
        if self.learning is not None:
            self.learning.close()
        if self.online is not None:
            self.online.stop()
        self.pool.close()

    @property
    def online(self) -> OnlineAnchors | None:
        """The online anchors past the checkpoint's span (None: the stream has no frames)."""
        return self.engine.timebase.online

    def _on_batch(self, batch: SensorBatch) -> None:
        """Ingest thread, after each batch is stored."""
        has_frames = batch.frames is not None and len(batch.frames)
        if self.learning is not None:
            self.learning.feed(batch)
            if self.engine.timeline is None and (len(batch.events) or has_frames):
                # learnt from the stream itself: the scene's clock is the stream's
                first = min(t for t in (batch.events.t[:1].tolist() + (
                    [int(batch.frames.t_us[0])] if has_frames else [])))
                self.engine.timeline = Timeline(first, first)
            if has_frames and self.engine.model is None and not self._origin_set:
                self._origin_set = True  # the scene starts at its first frame, as its models will
                tb = self.engine.timebase
                meta = replace(tb.meta, t_start_us=int(batch.frames.t_us[0]), channels=batch.frames.channels)
                self.engine.swap(FramesTimebase(meta, tb.frames))
        elif self.engine.timeline is None and len(batch.events):
            # A camera's clock is known at its first event; align it with the scene's start and loop
            # over the trained span (see live/clock.py).
            # With frames, online anchors carry it past the span instead: no loop.
            meta = self.engine.meta
            self.engine.timeline = Timeline(int(batch.events.t[0]), meta.t_start_us,
                                            None if self.online is not None
                                            else meta.t_end_us - meta.t_start_us + 1)
        tl = self.engine.timeline
        if has_frames and tl is not None:
            with self._swap:
                online = self.online
                if online is not None:  # (a swap may have given it this batch's frames already)
                    newest = online.newest_frame_us
                    fresh = batch.frames if newest is None else batch.frames.time_slice(newest + 1, 2**62)
                    if len(fresh):
                        online.on_frames(fresh, tl.scene_of)
        wm = self.ring.watermark_us
        if wm is not None:
            self.arrivals.record(wm)
        if self.signal is not None:
            self.signal.notify()

    # ------------------------------------------------------------------ health
    def health(self) -> tuple[bool, dict]:
        """(ready, details): ready when the model is loaded and the source delivers (or delivered); without
        a sensor, once the model is loaded."""
        ingest = self.ingest
        head = self.engine.head()
        if self.source is None:
            source_state = "none"
        else:
            source_state = ("error" if ingest is None or ingest.error is not None else
                            "ended" if ingest.finished else "streaming" if ingest.running else "stopped")
        ready = source_state in ("streaming", "ended", "none") and head is not None
        details = {
            "ready": ready,
            "model": "learning" if self.learning is not None and self.engine.model is None else "loaded",
            "device": self.settings.device,
            "source": source_state,
            "source_error": None if ingest is None or ingest.error is None else str(ingest.error),
            "events_in_ring": len(self.ring),
            "head_us": None if head is None else head[1],
            "uptime_s": round(time.time() - self.started_unix, 3),
        }
        return ready, details

    # ------------------------------------------------------------------ requests
    def size(self, width: int | None, height: int | None) -> tuple[int, int]:
        """Output size: the camera's by default; one side alone keeps the aspect ratio; capped."""
        native = self.engine.meta.intrinsics
        if width is None and height is None:
            width, height = native.width, native.height
        elif height is None:
            height = max(1, round(width * native.height / native.width))
        elif width is None:
            width = max(1, round(height * native.width / native.height))
        for name, value, cap in (("width", width, self.settings.max_width),
                                 ("height", height, self.settings.max_height)):
            if value < 1:
                raise invalid(name, f"{name} must be >= 1, got {value}")
            if value > cap:
                raise invalid(name, f"{name}={value} exceeds the server's limit of {cap} px")
        return int(width), int(height)

    def render_frame(self, t_us: int | None, pose: np.ndarray | None, width: int, height: int,
                     fmt: str, mode: str = "rgb") -> RenderedFrame:
        """Blocking (run on the pool): one render, ``data`` encoded in ``fmt`` (png | jpeg | raw); ``mode``
        what it shows (protocol.RENDER_MODES)."""
        t0 = time.perf_counter()
        try:
            rendered = self.engine.render(t_us, pose, width, height, mode=mode)
            t1 = time.perf_counter()
            data = encode(rendered.pixels, fmt, jpeg_quality=self.settings.jpeg_quality,
                          png_compress_level=self.settings.png_compress_level)
            for stage, seconds in (*rendered.stages.items(), ("encode", time.perf_counter() - t1)):
                self.metrics.render_stage.labels(stage).observe(seconds)
        except EdmcgsError:
            raise
        except Exception as exc:  # torch / numba / Pillow failures: a 500 with a message, not a crash
            raise RenderError(f"render failed: {type(exc).__name__}: {exc}") from exc
        ms = (time.perf_counter() - t0) * 1e3
        inst = rendered.instant
        near, far = (None, None) if rendered.depth_range is None else rendered.depth_range
        meta = protocol.FrameMeta(t_us=inst.t_us, t=self.engine.seconds_of(inst.t_us),
                                  anchor_us=inst.anchor_us, events=rendered.events, render_ms=round(ms, 3),
                                  width=width, height=height, channels=int(rendered.pixels.shape[2]),
                                  format=fmt, anchor=rendered.anchor, projected=rendered.projected,
                                  render_mode=rendered.mode, depth_near=near, depth_far=far,
                                  model_version=rendered.model_version)
        return RenderedFrame(meta, data, inst.window)

    def event_map(self, t_us: int | None, fmt: str) -> tuple[protocol.EventMapMeta, bytes]:
        """Blocking (run on the pool): GET /events' body, I_E of the window a render at ``t_us`` uses,
        as DV-style RGBA PNG or as the msgpack event map (protocol.py)."""
        try:
            instant, n_events, emap = self.engine.event_map(t_us)
            height, width = emap.shape
            meta = protocol.EventMapMeta(t_us=instant.t_us, t=self.engine.seconds_of(instant.t_us),
                                         anchor_us=instant.anchor_us, events=n_events, width=width,
                                         height=height)
            if fmt == "msgpack":
                return meta, protocol.pack(meta.to_message(emap.astype(protocol.EVENT_MAP_DTYPE).tobytes()))
            return meta, encode(event_rgba(emap), "png", png_compress_level=self.settings.png_compress_level)
        except EdmcgsError:
            raise
        except Exception as exc:  # numba / Pillow failures: a 500 with a message, not a crash
            raise RenderError(f"event map failed: {type(exc).__name__}: {exc}") from exc

    def scene(self) -> dict:
        """The body of GET /scene."""
        engine = self.engine
        tb = engine.timebase  # one model for the whole answer
        meta, model = tb.meta, tb.model
        intr = meta.intrinsics
        traj = meta.trajectory
        head = engine.head()
        ranges = engine.renderable(tb)
        info = self.source.info if self.source is not None else None
        t_end = meta.t_end_us if model is not None else meta.t_start_us if head is None else max(head[1],
                                                                                                  meta.t_start_us)
        return {
            "t_start_us": meta.t_start_us,
            "t_end_us": t_end,
            "duration_s": (t_end - meta.t_start_us) / 1e6,
            "anchors_us": [] if model is None else [int(a) for a in meta.anchors_us],
            "intrinsics": {"fx": intr.fx, "fy": intr.fy, "cx": intr.cx, "cy": intr.cy,
                           "width": intr.width, "height": intr.height},
            "event_size": {"width": meta.event_width, "height": meta.event_height},
            "trajectory": None if traj is None else {
                "t_us": [int(t) for t in traj.t_us], "c2w": [m.reshape(-1).tolist() for m in traj.c2w]},
            "channels": meta.channels,
            "has_event_branch": meta.has_event_branch,
            "num_gaussians": 0 if model is None else len(model.gaussians),
            "head_us": None if head is None else head[1],
            "head_t": None if head is None else engine.seconds_of(head[1]),
            "stream_head_us": None if head is None else head[0],
            "renderable": engine.range_dict(ranges[-1]) if ranges else None,
            "renderable_ranges": [engine.range_dict(r) for r in ranges],
            "tau_sources": engine.tau_ranges(),
            "training_views": None if model is None else training_views(model),
            "online": self.online_info(),
            "learning": None if self.learning is None else self.learning.info(),
            "source": None if info is None else {
                "sensor": info.sensor, "live": info.live, "width": info.width, "height": info.height,
                "has_frames": info.has_frames, "loop": self.inputs.loop,
                "speed": self.settings.speed if not info.live else None,
                "period_us": None if engine.timeline is None else engine.timeline.period_us},
            "playback": None if engine.playback is None else {   # no sensor: the clock of the head
                "speed": engine.playback.speed, "period_us": engine.playback.period_us, "loop": True},
            "limits": {"max_width": self.settings.max_width, "max_height": self.settings.max_height,
                       "stream_max_fps": self.settings.stream_max_fps},
            "formats": list(protocol.RENDER_FORMATS),
            "stream_formats": list(protocol.STREAM_FORMATS),
            "render_modes": list(protocol.RENDER_MODES),
        }

    def online_info(self) -> dict | None:
        """GET /scene's ``online``: the online anchors past the checkpoint's span (None: the stream has
        no frames)."""
        return None if self.online is None else self.online.info(self.engine.range_dict)

    # ------------------------------------------------------------------ metrics
    def _register_metrics(self) -> None:
        """The series read when scraped (metrics.Readings): counts kept by the ring, the pool, the cache
        and the online anchors."""
        gauge, counter, ring = self.metrics.readings.gauge, self.metrics.readings.counter, self.ring

        def dropped() -> dict[str, float]:
            s = ring.stats()
            out = {"overflow": s.overflowed, "late": s.late,
                   "invalid": 0 if self.source is None else self.source.stats.dropped}
            behind = getattr(self.source, "missed_events", None)  # a shared source this process lags
            if behind is not None:
                out["behind"] = behind
            return out

        gauge("edmcgs_up", "1 when the service is ready (model loaded, source delivering).",
              lambda: float(self.health()[0]))
        counter("edmcgs_events_ingested_total", "Events offered to the ring buffer.",
                lambda: ring.stats().pushed)
        counter("edmcgs_events_dropped_total", "Events dropped: ring overflow (oldest first), late "
                "(behind the watermark), invalid (rejected by the source's validation), behind (a shared "
                "source's batches this process fell too far behind to get).", dropped, "reason")
        counter("edmcgs_source_reconnects_total", "Times the source came back after going away (a camera "
                "unplugged and found again; a scene's shared source whose ingest replica was replaced).",
                lambda: float(getattr(self.source, "reconnects", 0)))
        counter("edmcgs_events_expired_total", "Events aged out of the ring's retention (a looping replay "
                "keeps two passes): older than any render can use, so not dropped.",
                lambda: ring.stats().expired)
        gauge("edmcgs_ring_events", "Events held in the ring buffer.", lambda: len(ring))
        gauge("edmcgs_ring_capacity_events", "Capacity of the ring buffer.", lambda: ring.capacity)
        gauge("edmcgs_ring_fill_ratio", "Ring buffer fill (0..1).", lambda: ring.stats().fill)
        counter("edmcgs_deform_cache_total", "Deformed-state lookups by result.",
                lambda: {"hit": self.engine.cache.hits, "miss": self.engine.cache.misses}, "result")
        counter("edmcgs_renders_rejected_total", "GET /render refused with 503: every render worker and "
                "queue slot taken.", lambda: self.pool.rejected)
        gauge("edmcgs_renders_in_flight", "Renders running or waiting for a worker.",
              lambda: self.pool.in_flight)
        if self.online is not None or self.learning is not None:
            register_online_metrics(self.metrics, lambda: self.online)
        if self.learning is not None:
            self.learning.register_metrics(self.metrics)
        gauge("edmcgs_stream_clients", "Open websocket streams.", lambda: self.metrics.stream_clients)
        counter("edmcgs_streams_refused_total", "Websocket streams refused: max_streams open.",
                lambda: self.metrics.streams_refused)
        gauge("edmcgs_stream_renders_in_flight", "Stream frames rendering or waiting for a worker.",
              lambda: self.pool.stream_in_flight)


def retain_passes(ring: EventRingBuffer, timeline: Timeline) -> None:
    """A looping replay keeps two passes of events and expires older ones: a render's window lies within
    one pass, and two retained passes keep the whole span renderable (clock.renderable). Without it the
    older passes filled the ring and overflowed it, continuously."""
    if timeline.period_us is not None:
        ring.retention_us = 2 * int(timeline.period_us) + 1


def replay_timeline(t_range_us: tuple[int, int], scene_start_us: int, scene_end_us: int,
                    loop: bool) -> Timeline:
    """The timeline of a replay whose file spans ``t_range_us`` (inclusive; see timeline.py).

    A file on the checkpoint's clock (its span overlaps the trained span) keeps its times; one on
    another clock is aligned by its first timestamp with the scene's start.
    """
    first, last = t_range_us
    period = last + 1 - first if loop else None
    same_clock = first <= scene_end_us and last >= scene_start_us
    if not same_clock:
        log.warning("the recording's clock [%d, %d] µs does not overlap the checkpoint's span [%d, %d] µs: "
                    "aligning its start with the scene's start", first, last, scene_start_us, scene_end_us)
    return Timeline(first, first if same_clock else scene_start_us, period)

