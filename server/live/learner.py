"""The learner: a process of its own beside the server (``learning.py`` starts and feeds it) that trains
EdMCGS on the stream's frames and events as they arrive, and publishes checkpoints the server swaps in.

    inbox ──> the stream so far (events, frames) ──> rounds, each over every anchor received when it
              began (frames at ``anchor_fps``; the frames between them held out and scored):
              a model lifted from those anchors, its networks warm-started from the round before
              (model/train/warm.py), trained ``steps`` (``first_steps`` at ``first_scale`` of the frames'
              size, then twice the round before at full size, up to the preset's iterations), published
              every ``publish_s`` (a new round's once it has trained each anchor as long as the model
              live did) and at the round's end.
              A round that ends with no new anchor goes on with the same model on the preset's whole
              schedule (then it trains on at the schedule's end), until new anchors start a round.
    stop ──>  the model and the stream saved: ``learned.ckpt`` (with its train state beside it) and
              ``learned.h5``; ``edmcgs train learned.h5 -o learned.ckpt --resume`` continues the run and
              ``edmcgs-serve --replay learned.h5 --checkpoint learned.ckpt`` serves it.

Messages in: ("batch", t, x, y, p, frame_t, frame_images) | ("stop",). Out: dicts with a ``kind``:
"published" (path, version, span, anchors, steps, Gaussians, held-out scores, CPU seconds), "saved"
(what ``save`` wrote), "error".
"""

from __future__ import annotations

import math
import os
import queue
import signal
import time
import traceback
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from edmcgs.errors import EdmcgsError
from edmcgs.server.live.config import LearnConfig

LEARNED_CKPT = "learned.ckpt"
LEARNED_REC = "learned.h5"
IDLE_WAIT_S = 0.2
"""How long the learner waits for the stream when it has nothing to train yet."""
CHUNK_STEPS = 5
"""Training steps between two looks at the inbox."""
SETTLE_STEPS = 50
"""Steps a round trains after adding Gaussians before a model of it goes live (street3d: published 10 steps
after a densification that added 53,000, a model drew the first second's moving pixels 0.08 dB below the
events integrated; 50 steps on, as at the next cadence, not)."""
REFILL_S = 0.01
"""How long an emptied inbox is waited on for more (``_drain``)."""


@dataclass
class Round:
    trainer: object
    recording: object
    """What the round learns from: the stream when it began (saved with its model, a resumable pair)."""
    steps: int
    """Where this round's training stops (then a new round, or the same model trains on)."""
    anchors: int
    """Anchors the round was built from."""
    full: int
    """The preset's iterations: the longest schedule a round gets."""
    preset: str = ""
    """The preset it trains (``LearnConfig.preset``, ``auto`` resolved)."""
    lengthened: bool = False
    """Whether the round runs past its own schedule (``Learner._lengthen``): new anchors end it at once."""


class Stream:
    """The stream received so far: events in chunks (joined when a round reads them) and every frame."""

    def __init__(self, width: int, height: int):
        self.width, self.height = width, height
        self._events: list[tuple[np.ndarray, ...]] = []
        self._frame_t: list[np.ndarray] = []
        self._frame_images: list[np.ndarray] = []
        self.events = 0
        self.frames = 0
        self.first_frame_us: int | None = None
        self.last_frame_us: int | None = None

    def add(self, t, x, y, p, frame_t, frame_images) -> None:
        if len(t):
            self._events.append((t, x, y, p))
            self.events += len(t)
        if frame_t is not None and len(frame_t):
            self._frame_t.append(frame_t)
            self._frame_images.append(frame_images)
            self.frames += len(frame_t)
            if self.first_frame_us is None:
                self.first_frame_us = int(frame_t[0])
            self.last_frame_us = int(frame_t[-1])

    def recording(self, config: LearnConfig):
        """The stream so far as a recording with what ``config`` knows of the camera, its frames split into
        anchors at ``anchor_fps`` and held-out frames (pipeline.split_frames)."""
        from edmcgs.pipeline import split_frames
        from edmcgs.sensor.events import Events
        from edmcgs.sensor.files.recording import Recording
        from edmcgs.sensor.frames import Frames

        if len(self._events) > 1:  # joined once: later rounds read one array per column
            self._events = [tuple(np.concatenate(c) for c in zip(*self._events, strict=True))]
        if len(self._frame_t) > 1:
            self._frame_t = [np.concatenate(self._frame_t)]
            self._frame_images = [np.concatenate(self._frame_images)]
        events = Events(*self._events[0]) if self._events else Events.empty()
        frames = Frames(self._frame_t[0], self._frame_images[0])
        intrinsics, trajectory = config.intrinsics, config.trajectory
        rec = Recording(self.width, self.height, events, frames,
                        intrinsics=None if intrinsics is None else np.asarray(intrinsics, np.float64),
                        trajectory_t_us=None if trajectory is None else trajectory[0],
                        trajectory_c2w=None if trajectory is None else trajectory[1],
                        contrast_threshold=config.contrast_threshold, sensor="learned from a stream")
        return split_frames(rec, fps=config.anchor_fps)


class Learner:
    """The rounds (the module's docstring): ``step`` trains a little and says what to publish."""

    def __init__(self, config: LearnConfig, stream: Stream, outbox):
        self.config, self.stream, self.outbox = config, stream, outbox
        self.round: Round | None = None
        self.model = None
        self.data = None
        self.version = 0
        self.published_at = 0.0  # set when the first round starts
        self.live_steps = 0
        """Training steps behind the last published model."""
        self.live_anchors = 0
        """Anchors of the last published model."""
        self.cpu_start = time.process_time()

    def anchors_available(self) -> int:
        """Anchors a round built now would have (frames at ``anchor_fps`` so far)."""
        first, last = self.stream.first_frame_us, self.stream.last_frame_us
        if first is None:
            return 0
        return math.floor((last - first) * self.config.anchor_fps / 1e6) + 1

    def step(self) -> bool:
        """Train one chunk, starting a round first when due; False when there is nothing to train yet."""
        rnd = self.round
        if rnd is None:
            if self.anchors_available() < self.config.min_anchors:
                return False
            self._new_round()
            self.published_at = time.monotonic()
        elif rnd.lengthened and self.anchors_available() > rnd.anchors:  # new anchors end it at once
            self._new_round()
        elif rnd.trainer.step >= rnd.steps:  # the round is over
            if self.anchors_available() > rnd.anchors:
                self._new_round()
            elif rnd.steps < rnd.full:  # no new anchor: the same model, on the preset's schedule
                self._lengthen()
            else:  # at the preset's schedule: it trains on at its end
                rnd.steps *= 2
        rnd = self.round
        for _ in range(CHUNK_STEPS):
            rnd.trainer.train_step()
        step = rnd.trainer.step
        # a new round's model goes live once it has trained each anchor as long as the one live did (or at
        # its round's end): a model with more anchors and fewer steps each draws what moves worse than the
        # one it replaces (street3d: 9 anchors at 150 steps replaced by 21 at 150, -0.22 dB on the moving
        # pixels against the events integrated), while the new span meanwhile shows the frame moved by
        # the events
        grown = rnd.trainer.grown_at
        due = time.monotonic() - self.published_at >= self.config.publish_s and \
            step * self.live_anchors >= self.live_steps * rnd.anchors and \
            (grown is None or step - grown >= SETTLE_STEPS)
        if step >= rnd.steps or due:
            self.publish()
        return True

    def _new_round(self) -> None:
        from edmcgs.model.train.trainer import Trainer
        from edmcgs.model.train.warm import warm_start
        from edmcgs.pipeline import build_config, default_preset, new_model, training_data

        cfg = self.config
        previous = self.round
        rec = self.stream.recording(cfg)
        if cfg.trajectory is None and cfg.poses == "auto":
            rec = self._with_poses(rec, None if previous is None else previous.recording)
        name = cfg.preset if cfg.preset != "auto" else \
            ("moving" if default_preset(rec)[0] == "moving" else "real")
        data = training_data(rec)
        base = build_config(name, list(cfg.overrides), rec)
        steps = cfg.first_steps if previous is None else min(2 * previous.steps, base.iterations)
        if previous is not None and previous.steps >= base.iterations:
            steps = base.iterations
        # the schedules (learning-rate decay, the event branch's warm-in) run over the round's steps; the
        # first round renders at first_scale of the frames' size, so that a model is live soon
        scale = base.train_scale if previous is not None else min(base.train_scale, cfg.first_scale)
        # (a fixed total per round: the round's steps, not the preset's per anchor window)
        model = new_model(data, base.replace(iterations=max(steps, 1), steps_per_window=0, train_scale=scale))
        if self.model is not None:
            previous.trainer.settle()
            warm_start(model, self.model)
        self.model, self.data = model, data
        self.round = Round(Trainer(model, data, progress=False), rec, steps, len(data.anchors_t_us),
                           base.iterations, preset=name)

    def _with_poses(self, rec, previous):
        """``rec`` with the poses structure from motion finds over its frames, in the world frame of the round
        before when both moved: the similarity fitted on the anchors they share carries the poses and points
        over, so that a pose a viewer holds means the same place after a swap. The first round maps its
        anchor frames only (its model is wanted soon: 9 anchors map in 2 s, their 42 frames in 20 CPU-s);
        later rounds map every frame received, because a hand-held camera's shake between anchors is not
        in their interpolation (street3d: the offline model scored 33.09 dB at its own poses of the
        held-out frames, 27.81 at poses interpolated between its anchors, the events integrated onto the
        last anchor 28.32). When it fails (too few frames registered, as the first anchors may), the round
        takes a still camera, said on the learner's output."""
        from dataclasses import replace

        from edmcgs.geometry import Similarity, Trajectory
        from edmcgs.pipeline import all_frames, estimated_poses

        mapped = replace(rec, held_out=None) if previous is None else rec
        try:
            out = estimated_poses(mapped, threads=self.config.threads)
        except EdmcgsError as exc:
            print(f"learner: no poses from {len(all_frames(mapped))} frames ({exc}); this round takes a "
                  "still camera", flush=True)
            return rec
        if previous is None:  # mapped without its held-out frames: they follow the anchors' trajectory
            out = replace(out, held_out=rec.held_out)
        if previous is None or previous.points_xyz is None or out.points_xyz is None:
            return out
        shared = np.intersect1d(previous.anchors.t_us, out.anchors.t_us)
        try:
            to_previous = Similarity.fit_poses(
                Trajectory(out.trajectory_t_us, out.trajectory_c2w).at(shared),
                Trajectory(previous.trajectory_t_us, previous.trajectory_c2w).at(shared))
        except EdmcgsError:  # the shared anchors did not move: frames that cannot be related
            return out
        return replace(out, trajectory_c2w=to_previous.poses(out.trajectory_c2w),
                       points_xyz=to_previous.points(out.points_xyz).astype(out.points_xyz.dtype))

    def _lengthen(self) -> None:
        """The round on the preset's whole schedule, the model and its optimizer kept: training goes on
        from its step as ``edmcgs train --resume --set iterations=N`` would, the schedules (learning rates,
        densification, the event branch's warm-in) read at the new length. Without it a stream that
        stopped growing (a replay's end, a camera held still) would train on at a short schedule's end, its
        learning rates at their floor, and never reach the preset's model. One long schedule, not a
        doubling each time: every restart of the decay cost against the offline run (traffic: 0.55 dB
        behind at 85 % of its CPU time with doublings, 0.02 dB at 101 % without); publishing every
        ``publish_s`` keeps the models coming, and new anchors end the round at once."""
        rnd = self.round
        rnd.steps = rnd.full
        rnd.lengthened = True
        rnd.trainer.reschedule(rnd.steps)

    def publish(self, path: Path | None = None) -> Path:
        """Save the current model (a final checkpoint: what the server loads) and report it."""
        from edmcgs.model.checkpoint import save_checkpoint

        self.version += 1
        path = path or self.config.workdir / f"learned-{self.version:04d}.ckpt"
        trainer = self.round.trainer
        trainer.settle()
        model = trainer.model
        was_training = model.training
        model.eval()
        save_checkpoint(model, path)
        model.train(was_training)
        scores = trainer.evaluate(self.config.eval_frames) if self.data.evaluable().size else None
        meta = model.meta
        self.outbox.put({"kind": "published", "path": str(path), "version": self.version,
                         "span_us": [int(meta.t_start_us), int(meta.t_end_us)],
                         "anchors": len(meta.anchors_us), "steps": trainer.step, "preset": self.round.preset,
                         "camera": _camera(self.round.recording),
                         "round_steps": self.round.steps,
                         "gaussians": len(model.gaussians), "heldout": scores,
                         "cpu_s": time.process_time() - self.cpu_start,
                         "frames": self.stream.frames, "events": self.stream.events})
        self.published_at = time.monotonic()
        self.live_steps, self.live_anchors = trainer.step, self.round.anchors
        # the server may still be reading the one before this one
        for old in sorted(self.config.workdir.glob("learned-*.ckpt"))[:-2]:
            old.unlink(missing_ok=True)
        return path

    def save(self) -> dict:
        """What continuing needs: the model with its train state beside it, and the recording it learns
        from (the stream when its round began: ``edmcgs train --resume`` checks they belong together);
        before any round, the stream so far."""
        from edmcgs.model.train.resume import save_final
        from edmcgs.sensor.files.recording import write_recording

        cfg = self.config
        out = {"kind": "saved", "checkpoint": None, "recording": None}
        if self.stream.frames:
            rec = self.stream.recording(cfg) if self.round is None else self.round.recording
            write_recording(cfg.workdir / LEARNED_REC, rec)
            out["recording"] = str(cfg.workdir / LEARNED_REC)
        if self.round is not None:
            trainer, path = self.round.trainer, cfg.workdir / LEARNED_CKPT
            trainer.model.eval()
            save_final(trainer.model, path, trainer.train_state())  # the two as one unit
            out.update(checkpoint=str(path), steps=trainer.step, version=self.version)
        return out


def _camera(rec) -> str:
    """How the round's camera is known: ``stated``, ``estimated: moving`` (or ``turning``, ``still``), or
    ``still`` when nothing said otherwise."""
    poses = rec.metadata.get("poses")
    if poses is None:
        return "still" if rec.trajectory_t_us is None else "stated"
    return "estimated: " + ("still" if poses["static"] else "turning" if poses["rotation_only"] else "moving")


def _drain(inbox, wait: float) -> list:
    """Every message waiting (for the first, up to ``wait`` s), so that training never lags the stream by
    a queue. The pipe under the queue holds a few dozen kB: the server's side refills it as it is read, so
    the next message is waited for briefly before the queue counts as empty."""
    out = []
    try:
        out.append(inbox.get(timeout=wait) if wait > 0 else inbox.get_nowait())
        while True:
            out.append(inbox.get(timeout=REFILL_S))
    except queue.Empty:
        return out


def main(inbox, outbox, config: LearnConfig, width: int, height: int) -> None:
    """The learner process: ``learning.Learning`` starts it with its queues."""
    import numba
    import torch

    # Ctrl-C (and a service manager's SIGTERM) reach the whole process group: the server says when to stop,
    # after it has stopped serving, and the learner saves then (or when the server is gone)
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, signal.SIG_IGN)
    parent = os.getppid()
    torch.set_num_threads(config.threads)
    numba.set_num_threads(min(config.threads, numba.config.NUMBA_NUM_THREADS))
    stream = Stream(width, height)
    learner = Learner(config, stream, outbox)
    idle = True
    try:
        while True:
            for msg in _drain(inbox, IDLE_WAIT_S if idle else 0.0):
                if msg[0] == "stop":
                    outbox.put(learner.save())
                    return
                stream.add(*msg[1:])
            if os.getppid() != parent:  # the server died without a word: keep what was learnt
                learner.save()
                return
            idle = not learner.step()
    except EdmcgsError as exc:
        outbox.put({"kind": "error", "error": str(exc)})
    except Exception as exc:  # reported, never silent: the server keeps serving what it has
        outbox.put({"kind": "error", "error": f"{type(exc).__name__}: {exc}",
                    "traceback": traceback.format_exc()})
