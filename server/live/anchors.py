"""Online anchors: the stream's APS frames past the checkpoint's span become anchors while it runs.

    ingest thread: frame at T past the span ──> refused (counted by reason) or
                   predicted: the previous anchor's state + g(events [prev, T))  ──> published
                   (g: the transition chosen past the span, below)
                   ──> one-slot fit queue (newest wins; the one it replaces counts as skipped)
    fit thread:    every candidate transition (g_phi, the checkpoint's distilled one, none) predicts
                   the frame from the anchor before it; the one with the lowest mean loss over the last
                   EVIDENCE frames becomes g ("select"; or one fixed by ``transition``); then a bounded
                   number of steps against the frame from this frame's best prediction
                   (model/online/correct.py) ──> published as corrected; its residual carried on to the
                   anchors predicted from it meanwhile; optionally (finetune_steps > 0) a copy of g learns
                   from the correction and replaces it

    render:        the anchor's state moved by g(events since it) (``Timebase.state``); of the event
                   camera's own view, projected onto the events since the anchor's frame (``project``)

Anchors are keyed by stream time (a looping replay passes the same scene times again; each pass chains
from the checkpoint's last anchor anew). The store is bounded (``capacity``) and drops anchors whose
events the ring no longer holds. Readers (renders) take the published tuple without a lock and never
wait for a fit.
"""

from __future__ import annotations

import logging
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np
import torch

from edmcgs.errors import WindowUnavailable
from edmcgs.model import online as model_online
from edmcgs.model.dynamic import EdMCGS
from edmcgs.model.motion.gaussians import GaussianState
from edmcgs.sensor.buffer.ring import EventRingBuffer
from edmcgs.sensor.event_map import accumulate
from edmcgs.sensor.frames import Frames
from edmcgs.server.live.config import OnlineConfig
from edmcgs.server.live.transitions import Transitions
from edmcgs.server.metrics import Metrics

log = logging.getLogger("edmcgs.server")

REFUSED_REASONS = ("size", "channels", "timestamp")
SKIPPED_REASONS = ("superseded",)
MAX_GAP_US = 1_000_000
"""An anchor farther than this from the one before it starts the chain again (``_predict``): the
transition learnt gaps of one anchor period, and seconds of events say little it can use."""
SWITCH_INTERVAL_S = 0.0005
"""The GIL switch interval while fitting (see ``start``)."""


@dataclass(frozen=True)
class OnlineAnchor:
    stream_us: int
    """The frame's time on the stream clock (the key)."""
    t_us: int
    """Its scene time (past the checkpoint's span)."""
    motion: model_online.Motion
    """Control-point (translations, rotations) at the anchor."""
    corrected: bool
    """False: the prediction; True: fitted to the frame."""
    version: int
    """Bumped whenever the state changes (the deform cache keys on it)."""
    pose: np.ndarray | None
    """The frame's camera-to-world, when the stream gives one."""
    spawned: GaussianState | None = None
    """Gaussians added for what the frame showed that the carried-forward window lacked (``spawn``);
    a prediction inherits the anchor before it's."""
    colors: torch.Tensor | None = None
    """Per-Gaussian colour offsets [N, C] learnt online (``colour_lr``); a prediction inherits the anchor
    before it's, and each correction refines them."""
    frame: np.ndarray | None = None
    """The frame itself (uint8 [H, W, C], read-only): what renders of the event camera's view from this
    anchor are projected onto with the events since it (``project``; server/engine.py)."""


def _frozen(image: np.ndarray) -> np.ndarray:
    """A read-only copy (the source may reuse its buffer; readers share this one)."""
    frame = image.copy()
    frame.flags.writeable = False
    return frame


class OnlineAnchors:
    """The online anchor store, its predictor (called by the ingest thread) and its fit worker."""

    def __init__(self, model: EdMCGS, ring: EventRingBuffer, config: OnlineConfig | None = None, *,
                 pose: Callable[[int], np.ndarray | None] | None = None):
        """config: how they run (config.py); pose: the event camera's pose at a scene time past the span
        when a frame brings none (default: the checkpoint's trajectory, clamped to its span)."""
        self.model, self.ring = model, ring
        self.config = config = config or OnlineConfig()
        self.transitions = Transitions(model, config.transition)
        # Only a model drawn in anchor windows lacks Gaussians for what enters the view past its span.
        self.spawn_limit = config.spawn if model_online.last_window(model) is not None else 0
        self.last_finetune: tuple[float, float] | None = None  # (loss before, after) of the last one
        self.fit_enabled = config.fit and config.fit_steps > 0
        self.pose = pose or self._trajectory_pose
        meta = model.meta
        self.end_us = int(meta.t_end_us)
        self.last_ckpt_us = int(meta.anchors_us[-1])
        self.size = (meta.intrinsics.width, meta.intrinsics.height)
        self._anchors: tuple[OnlineAnchor, ...] = ()  # published, oldest first; replaced whole
        self._lock = threading.Lock()  # writers only
        self._newest_frame_us: int | None = None
        self._span_frame: tuple[int, np.ndarray] | None = None  # (stream µs, frame) at the last ckpt anchor
        self.refused = dict.fromkeys(REFUSED_REASONS, 0)
        self.skipped = dict.fromkeys(SKIPPED_REASONS, 0)
        self.predicted = 0
        self.restarted = 0
        """Anchors that started the chain again (the events since the one before gone, or too long)."""
        self.corrected = 0
        self.expired = 0
        self.last_fit_s: float | None = None
        self.last_loss: tuple[float, float] | None = None
        self.fit_seconds: list[float] = []  # recent, for /scene
        self._slot: tuple[OnlineAnchor, np.ndarray] | None = None
        self._fitting = False
        self._cv = threading.Condition()
        self._stop = False
        self.on_fit: Callable[[float, float, float], None] | None = None  # (seconds, loss before, after)
        self._thread: threading.Thread | None = None
        model.requires_grad_(False)  # the networks and canonical Gaussians are frozen

    # ------------------------------------------------------------------ lifecycle
    def start(self) -> OnlineAnchors:
        if self.fit_enabled:
            # The fit is thousands of small torch ops, each taking the GIL back; at Python's default 5 ms
            # switch interval the ingest and request threads starve it (figures in reports/online.md).
            # Process-wide, and only ever lowered.
            sys.setswitchinterval(min(sys.getswitchinterval(), SWITCH_INTERVAL_S))
            self._thread = threading.Thread(target=self._worker, name="edmcgs-online-fit", daemon=True)
            self._thread.start()
        return self

    def stop(self, timeout: float = 5.0) -> None:
        with self._cv:
            self._stop = True
            self._cv.notify_all()
        if self._thread is not None:
            self._thread.join(timeout)

    def _trajectory_pose(self, t_us: int) -> np.ndarray | None:
        """The checkpoint's camera at a scene time (clamped to its span), or None without a trajectory."""
        traj = self.model.meta.trajectory
        return None if traj is None else traj.at(int(t_us))

    # ------------------------------------------------------------------ readers (no lock)
    def anchors(self) -> tuple[OnlineAnchor, ...]:
        return self._anchors

    def frame_at(self, stream_us: int) -> np.ndarray | None:
        """The stream's frame at ``stream_us`` where it starts renders past the span: an online anchor's,
        or the one at the checkpoint's last anchor (this pass's); else None."""
        anchor = self.get(stream_us)
        if anchor is not None:
            return anchor.frame
        span = self._span_frame
        return span[1] if span is not None and span[0] == stream_us else None

    @property
    def newest_frame_us(self) -> int | None:
        """The newest frame taken (stream µs), None before the first."""
        return self._newest_frame_us

    def get(self, stream_us: int) -> OnlineAnchor | None:
        for a in reversed(self._anchors):
            if a.stream_us == stream_us:
                return a
            if a.stream_us < stream_us:
                return None
        return None

    def tau(self, stream_t: int, scene_t: int) -> int:
        """tau on the stream clock for a time past the span: the newest online anchor at or before it
        in this pass, else the checkpoint's last anchor (in this pass)."""
        ckpt = stream_t - (int(scene_t) - self.last_ckpt_us)
        for a in reversed(self._anchors):
            if a.stream_us <= stream_t:
                return a.stream_us if a.stream_us > ckpt else ckpt
        return ckpt

    def advance(self, motion: model_online.Motion, event_map, ev_c2w) -> model_online.Motion:
        """An online anchor's ``motion`` moved by the events since it (``event_map``), by the transition
        chosen past the span (renders and predictions)."""
        transition = self.transitions.module
        if transition is None:
            return motion
        return model_online.advance(self.model, motion, event_map, ev_c2w, transition)

    @property
    def queue_depth(self) -> int:
        return int(self._slot is not None) + int(self._fitting)

    # ------------------------------------------------------------------ ingest thread
    def on_frames(self, frames: Frames, scene_of: Callable[[int], int]) -> None:
        """New frames of the stream (ingest thread, after their events are in the ring)."""
        for i in range(len(frames)):
            image = np.asarray(frames.images[i])
            if image.ndim == 2:
                image = image[..., None]
            t = int(frames.t_us[i])
            if (image.shape[1], image.shape[0]) != self.size:
                self._refuse("size", f"frame at {t} µs is {image.shape[1]}x{image.shape[0]}, the "
                             "checkpoint's "
                             f"camera is {self.size[0]}x{self.size[1]}")
                continue
            if image.shape[2] != self.model.meta.channels or image.dtype != np.uint8:
                self._refuse("channels", f"frame at {t} µs has {image.shape[2]} {image.dtype} channels, the "
                             f"checkpoint renders {self.model.meta.channels} uint8")
                continue
            if self._newest_frame_us is not None and t <= self._newest_frame_us:
                self._refuse("timestamp", f"frame at {t} µs is not after the newest frame "
                             f"({self._newest_frame_us} µs)")
                continue
            self._newest_frame_us = t
            scene_t = scene_of(t)
            if scene_t <= self.end_us:  # within the checkpoint's span its own anchors rule
                if scene_t == self.last_ckpt_us:  # renders past the span start from it until the first
                    self._span_frame = (t, _frozen(image))  # online anchor
                continue
            pose = None if frames.poses is None else np.asarray(frames.poses[i], np.float64)
            self._predict(t, scene_t, image, pose)

    def _refuse(self, reason: str, message: str) -> None:
        self.refused[reason] += 1
        log.warning("frame refused (%s): %s", reason, message)

    def _predict(self, t: int, scene_t: int, image: np.ndarray, pose) -> None:
        model = self.model
        with self._lock:
            prev_stream = self.tau(t - 1, scene_t - 1)
            prev = self.get(prev_stream)
            events = None
            if t - prev_stream <= MAX_GAP_US:
                try:
                    events = self.ring.slice(prev_stream, t)
                except WindowUnavailable:  # left the ring
                    pass
            c2w = pose if pose is not None else self.pose(scene_t)  # the event camera at the frame
            if events is None:
                # The chain starts again here (a ring that dropped its events, a model learnt far behind
                # the head): the model's own motion at this time, corrected against the frame.
                self.restarted += 1
                prev, motion = None, model_online.checkpoint_motion(model, scene_t)
            else:
                emap = (accumulate(events, model.meta.event_width, model.meta.event_height)
                        if len(events) else None)
                base = model_online.checkpoint_motion(model, scene_t) if prev is None else prev.motion
                motion = self.advance(base, emap, c2w)
            anchor = OnlineAnchor(t, scene_t, motion, False, 0, pose, None if prev is None else prev.spawned,
                                  None if prev is None else prev.colors, _frozen(image))
            self._publish((*self._anchors, anchor))
            self.predicted += 1
        if self.fit_enabled:
            with self._cv:
                if self._slot is not None:
                    self.skipped["superseded"] += 1
                self._slot = (anchor, image)
                self._cv.notify()

    def _publish(self, anchors: tuple[OnlineAnchor, ...]) -> None:
        """Lock held: bound the store by capacity and by the ring's oldest event, then swap."""
        stats = self.ring.stats()
        floor = stats.oldest_us if (stats.overflowed or stats.expired) else None
        keep = [a for a in anchors if floor is None or a.stream_us > floor]
        keep = keep[-self.config.capacity:]
        self.expired += len(anchors) - len(keep)
        self._anchors = tuple(keep)

    # ------------------------------------------------------------------ fit thread
    def _worker(self) -> None:
        torch.set_num_threads(1)
        while True:
            with self._cv:
                while self._slot is None and not self._stop:
                    self._cv.wait()
                if self._stop:
                    return
                anchor, image = self._slot
                self._slot, self._fitting = None, True
            try:
                self._fit(anchor, image)
            except Exception:  # a fit that fails leaves the prediction in place
                log.exception("online anchor fit at %d µs failed", anchor.stream_us)
            finally:
                self._fitting = False

    def _fit(self, anchor: OnlineAnchor, image: np.ndarray) -> None:
        current = self.get(anchor.stream_us)
        if current is None:
            return  # expired meanwhile
        c2w = anchor.pose if anchor.pose is not None else self.pose(anchor.t_us)
        if c2w is None:
            return
        t0 = time.perf_counter()
        cfg = self.config
        start = self._select(current, image, c2w) if self.transitions.select else current.motion
        (trans, _), colors, before, after = model_online.correct(
            self.model, start, image, c2w, self.model.meta.intrinsics, steps=cfg.fit_steps,
            lr=cfg.fit_lr, scale=cfg.fit_scale, colors=current.colors, colour_lr=cfg.colour_lr)
        spawned = current.spawned
        if self.spawn_limit:
            state = model_online.state_of(self.model, (trans, current.motion[1]), colors)
            spawned = model_online.spawn(self.model, state, image, c2w, self.model.meta.intrinsics,
                                         limit=self.spawn_limit)
        seconds = time.perf_counter() - t0
        delta = trans - current.motion[0]
        with self._lock:
            out = []
            for a in self._anchors:
                if a.stream_us == anchor.stream_us:
                    a = replace(a, motion=(a.motion[0] + delta, a.motion[1]), corrected=True,
                                version=a.version + 1, spawned=spawned, colors=colors)
                elif a.stream_us > anchor.stream_us and not a.corrected:
                    # predicted from this anchor's prediction: carry the correction on
                    a = replace(a, motion=(a.motion[0] + delta, a.motion[1]), version=a.version + 1,
                                colors=colors)
                out.append(a)
            self._publish(tuple(out))
        self.corrected += 1
        if cfg.finetune_steps > 0:
            self._finetune(anchor, trans, c2w)
            seconds = time.perf_counter() - t0
        self.last_fit_s, self.last_loss = seconds, (before, after)
        self.fit_seconds = [*self.fit_seconds[-63:], seconds]
        if self.on_fit is not None:
            self.on_fit(seconds, before, after)

    def _select(self, anchor: OnlineAnchor, image: np.ndarray, c2w: np.ndarray) -> model_online.Motion:
        """Fit thread: every candidate predicts this frame from the anchor before it (as it stands now, most
        likely corrected) by the events between them; each loss joins that candidate's evidence, and the
        one with the lowest mean over the last EVIDENCE frames moves the anchors past the span from now on.
        Returns this frame's best prediction, where its correction starts."""
        model = self.model
        since = self._since_previous(anchor)
        if since is None or since[1] is None:
            return anchor.motion  # no events: every candidate predicts the same
        base, emap = since
        names = list(self.transitions.candidates)
        predictions = [base if g is None else model_online.advance(model, base, emap, c2w, g)
                       for g in self.transitions.candidates.values()]
        losses = model_online.prediction_losses(model, predictions, anchor.spawned, image, c2w,
                                                model.meta.intrinsics, scale=self.config.fit_scale,
                                                colors=anchor.colors)
        self.transitions.record(dict(zip(names, losses, strict=True)))
        return predictions[int(np.argmin(losses))]

    def _finetune(self, anchor: OnlineAnchor, corrected: torch.Tensor, c2w: np.ndarray) -> None:
        """Fit thread: let a copy of the transition learn to predict the corrected anchor from the one
        before it by the events between them, then publish the copy (as that candidate) for the next
        predictions and renders."""
        since = self._since_previous(anchor)
        current = self.transitions.module
        if since is None or current is None:
            return
        tuned = model_online.finetune(self.model, current, since[0], since[1], c2w, corrected,
                                      steps=self.config.finetune_steps, lr=self.config.finetune_lr)
        if tuned is not None:
            self.last_finetune = tuned[1:]
            self.transitions.replace(tuned[0])

    def _since_previous(self, anchor: OnlineAnchor) -> tuple[model_online.Motion, np.ndarray | None] | None:
        """(the motion of the anchor before ``anchor`` as it stands now, the event map between them; None
        without events), or None when those events have left the ring or span more than MAX_GAP_US (the
        chain started again at ``anchor``)."""
        model = self.model
        prev_stream = self.tau(anchor.stream_us - 1, anchor.t_us - 1)
        if anchor.stream_us - prev_stream > MAX_GAP_US:
            return None
        prev = self.get(prev_stream)
        base = prev.motion if prev is not None else model_online.checkpoint_motion(model, anchor.t_us)
        try:
            events = self.ring.slice(prev_stream, anchor.stream_us)
        except WindowUnavailable:
            return None
        emap = accumulate(events, model.meta.event_width, model.meta.event_height) if len(events) else None
        return base, emap

    def wait_idle(self, timeout: float = 30.0) -> bool:
        """Until the fit queue is empty and no fit runs (tests, benchmarks)."""
        deadline = time.monotonic() + timeout
        while self.queue_depth and time.monotonic() < deadline:
            time.sleep(0.01)
        return not self.queue_depth

    # ------------------------------------------------------------------ what the service shows
    def info(self, range_dict: Callable[[tuple[int, int]], dict]) -> dict:
        """GET /scene's ``online`` (``range_dict``: scene µs interval -> the protocol's range)."""
        anchors, cfg = self.anchors(), self.config
        fits = sorted(self.fit_seconds)
        return {
            "span": None if not anchors else range_dict((anchors[0].t_us, anchors[-1].t_us)),
            "anchors": [{"t_us": a.t_us, "stream_us": a.stream_us, "corrected": a.corrected}
                        for a in anchors],
            "capacity": cfg.capacity,
            "predicted": self.predicted, "corrected": self.corrected, "expired": self.expired,
            "restarted": self.restarted,
            "skipped": dict(self.skipped), "refused": dict(self.refused),
            "queue_depth": self.queue_depth,
            "project": cfg.project,
            "transition": self.transitions.info(),
            "fit": {"steps": cfg.fit_steps if self.fit_enabled else 0, "scale": cfg.fit_scale,
                    "colour_lr": cfg.colour_lr, "last_s": self.last_fit_s,
                    "median_s": fits[len(fits) // 2] if fits else None,
                    "last_loss": None if self.last_loss is None else {
                        "before": self.last_loss[0], "after": self.last_loss[1]}},
        }


def register_metrics(metrics: Metrics, current: Callable[[], OnlineAnchors | None]) -> None:
    """The online anchors' series in the service's metrics, read when scraped from ``current()``, the
    online anchors served now (a cold start swaps in new ones with each learnt model: their counts start
    over, which Prometheus reads as a counter reset)."""
    gauge, counter = metrics.readings.gauge, metrics.readings.counter

    def read(fn, empty):
        return lambda: empty if (online := current()) is None else fn(online)

    gauge("edmcgs_online_anchors", "Online anchors held past the checkpoint's span.",
          read(lambda o: float(len(o.anchors())), 0.0))
    counter("edmcgs_online_anchors_total", "Online anchors by outcome: predicted, corrected (fitted to their "
            "frame), expired (out of the bounded store).",
            read(lambda o: {"predicted": o.predicted, "corrected": o.corrected, "expired": o.expired,
                            "restarted": o.restarted},
                 {"predicted": 0, "corrected": 0, "expired": 0, "restarted": 0}), "result")
    counter("edmcgs_online_anchors_skipped_total", "Online anchors not corrected (superseded: a newer frame "
            "took the one-slot fit queue).",
            read(lambda o: dict(o.skipped), dict.fromkeys(SKIPPED_REASONS, 0)), "reason")
    counter("edmcgs_frames_refused_total", "Stream frames refused as anchors, by reason (size, channels, "
            "timestamp: not after the newest frame).",
            read(lambda o: dict(o.refused), dict.fromkeys(REFUSED_REASONS, 0)), "reason")
    gauge("edmcgs_online_fit_queue_depth", "Online anchors waiting for or in a fit (0..2).",
          read(lambda o: float(o.queue_depth), 0.0))
    gauge("edmcgs_online_fit_loss", "L1 photometric loss of the last correction, after its steps.",
          read(lambda o: float("nan") if o.last_loss is None else o.last_loss[1], float("nan")))
