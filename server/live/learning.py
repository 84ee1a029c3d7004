"""A cold start: the service learns its model while it serves (``edmcgs-serve --replay REC`` or ``--live``
with no checkpoint). This is the server's side of the learner (``learner.py``, its own process; a scene
on Ray shares one learner between its replicas, ``ray_serve/learner.py``).

    ingest thread ──> feed(batch) ──> the learner's inbox (a queue: the ingest never waits)
    the learner publishes a checkpoint ──> a thread here loads it ──> on_model(model, report): the
    service builds its timebase off the render path and swaps it into the engine (service.py)
    close ──> the learner saves ``learned.ckpt`` and ``learned.h5`` and ends

Until the first model the engine renders the stream's frames moved by the events since
(``timebase.FramesTimebase``); ``info`` is what GET /scene and /metrics say of the learner.
"""

from __future__ import annotations

import logging
import multiprocessing
import queue
import threading
import time
from collections.abc import Callable

from edmcgs.errors import EdmcgsError
from edmcgs.sensor.sources.base import SensorBatch
from edmcgs.server.live import learner
from edmcgs.server.live.config import LearnConfig

log = logging.getLogger("edmcgs.server")


class LearnerView:
    """What the service holds of a learner, wherever it runs: the models it hands over (``on_model``),
    the one served, and what /scene and /metrics say of it. ``Learning`` (its own process here) and a
    Ray scene's ``RemoteLearning`` (one learner shared by the scene's replicas) are the two."""

    def __init__(self, config: LearnConfig):
        self.config = config
        self.on_model: Callable[[object, dict], None] | None = None
        """Called with each published model (loaded) and the learner's report, on this side's reader
        thread (the service builds it into a timebase and swaps it in)."""
        self.published: dict | None = None
        """The last published model's report (learner.py), with ``live_unix`` once it is served."""
        self.saved: dict | None = None
        """What the learner saved when it stopped."""
        self.error: str | None = None
        self.fed = {"batches": 0, "events": 0, "frames": 0}
        self.started_unix: float | None = None

    @property
    def running(self) -> bool:
        raise NotImplementedError

    def _take(self, report: dict, path) -> None:
        """Load the published checkpoint at ``path``, hand it to ``on_model``, and count it served."""
        from edmcgs.model.checkpoint import load_checkpoint

        try:
            model = load_checkpoint(path)
            if self.on_model is not None:
                self.on_model(model, report)
        except EdmcgsError as exc:  # the last model stays: the next one may load
            log.error("learned model %d not taken: %s", report["version"], exc)
            return
        self.published = {**report, "live_unix": time.time()}
        scores = report.get("heldout") or {}
        log.info("learned model %d live: %d anchors, step %d, held-out PSNR %s", report["version"],
                 report["anchors"], report["steps"],
                 f"{scores['psnr']:.2f} dB" if "psnr" in scores else "(no held-out frame yet)")

    def register_metrics(self, metrics) -> None:
        """The learner's series in the service's metrics (read when scraped)."""
        gauge, counter = metrics.readings.gauge, metrics.readings.counter

        def model(key, empty=float("nan")):
            return lambda: empty if self.published is None else float(self.published[key])

        gauge("edmcgs_learned_model_version", "The learnt model served now (0: none yet, renders are the "
              "stream's frames moved by the events).", model("version", 0.0))
        gauge("edmcgs_learned_span_seconds", "The stream time the served model learnt.",
              lambda: 0.0 if self.published is None else
              (self.published["span_us"][1] - self.published["span_us"][0]) / 1e6)
        gauge("edmcgs_learner_steps", "Training steps behind the served model (its round's).",
              model("steps", 0.0))
        gauge("edmcgs_learner_cpu_seconds", "The learner's CPU seconds when it published the served model.",
              model("cpu_s", 0.0))
        gauge("edmcgs_learned_heldout_psnr", "The served model's PSNR on stream frames it was not trained on "
              "(NaN: none yet).", lambda: float("nan") if self.published is None
              or not self.published.get("heldout") else float(self.published["heldout"]["psnr"]))
        gauge("edmcgs_learner_up", "1 while the learner runs.", lambda: float(self.running))
        counter("edmcgs_learner_fed_total", "What the server gave the learner.",
                lambda: {k: float(v) for k, v in self.fed.items()}, "what")

    def info(self) -> dict:
        """GET /scene's ``learning``."""
        pub = self.published
        return {
            "workdir": str(self.config.workdir),
            "preset": self.config.preset,
            "anchor_fps": self.config.anchor_fps,
            "running": self.running,
            "error": self.error,
            "fed": dict(self.fed),
            "version": None if pub is None else pub["version"],
            "model": None if pub is None else {
                "version": pub["version"], "span_us": pub["span_us"], "anchors": pub["anchors"],
                "steps": pub["steps"], "gaussians": pub["gaussians"], "cpu_s": pub["cpu_s"],
                "preset": pub["preset"], "camera": pub["camera"],
                "heldout": pub["heldout"], "live_unix": pub["live_unix"]},
            "started_unix": self.started_unix,
            "saved": self.saved,
        }


class Learning(LearnerView):
    """The learner in a process of its own. config: how it trains; width, height: the stream's event
    resolution."""

    def __init__(self, config: LearnConfig, width: int, height: int):
        super().__init__(config)
        config.workdir.mkdir(parents=True, exist_ok=True)
        ctx = multiprocessing.get_context("spawn")  # a fresh interpreter: no copy of the server's threads
        self.inbox, self.outbox = ctx.Queue(), ctx.Queue()
        self.process = ctx.Process(target=learner.main, name="edmcgs-learner", daemon=True,
                                   args=(self.inbox, self.outbox, config, width, height))
        self._saved = threading.Event()
        self._reader: threading.Thread | None = None

    @property
    def running(self) -> bool:
        return self.process.is_alive()

    def start(self) -> Learning:
        self.process.start()
        self.started_unix = time.time()
        self._reader = threading.Thread(target=self._read, name="edmcgs-learning", daemon=True)
        self._reader.start()
        return self

    def feed(self, batch: SensorBatch) -> None:
        """Ingest thread: the batch to the learner (copied by the queue; never blocks)."""
        ev, frames = batch.events, batch.frames
        has_frames = frames is not None and len(frames)
        if not len(ev) and not has_frames:
            return
        self.inbox.put(("batch", ev.t, ev.x, ev.y, ev.p, frames.t_us if has_frames else None,
                        frames.images if has_frames else None))
        self.fed["batches"] += 1
        self.fed["events"] += len(ev)
        self.fed["frames"] += len(frames) if has_frames else 0

    def _read(self) -> None:
        while True:
            try:
                report = self.outbox.get(timeout=1.0)
            except queue.Empty:
                if not self.process.is_alive():
                    if self.saved is None and self.error is None:
                        self.error = f"the learner exited with code {self.process.exitcode}"
                        log.error("%s", self.error)
                    self._saved.set()
                    return
                continue
            kind = report["kind"]
            if kind == "published":
                self._take(report, report["path"])
            elif kind == "saved":
                self.saved = report
                self._saved.set()
                return
            elif kind == "error":
                self.error = report["error"]
                log.error("the learner failed: %s%s", report["error"],
                          "\n" + report["traceback"] if "traceback" in report else "")

    def close(self, timeout: float = 120.0) -> dict | None:
        """Ask the learner to save what it learnt and end; returns what it saved (None: nothing in time)."""
        if self.process.is_alive():
            self.inbox.put(("stop",))
            self._saved.wait(timeout)
        self.process.join(30.0)  # torch's teardown takes seconds on a loaded machine
        if self.process.is_alive():
            self.process.kill()
            self.process.join(5.0)
        for q in (self.inbox, self.outbox):
            q.close()
            q.cancel_join_thread()  # what the learner did not read is not waited for
        if self.saved and self.saved.get("checkpoint"):
            log.info("the learner saved %s and %s: edmcgs train %s -o %s --resume continues it",
                     self.saved["checkpoint"], self.saved["recording"], self.saved["recording"],
                     self.saved["checkpoint"])
        return self.saved
