"""A cold-start scene on Ray: one learner for the scene, its models swapped into every render replica.

    SceneIngest (the scene's one source) ──> SceneLearner (one replica): reads the shared stream as a
        render replica does (``RemoteSource``) and feeds ``Learning``, the single-process learner
        (its own process beside the actor), which publishes checkpoints
    each render replica's ``RemoteLearning`` asks the learner every ``POLL_S`` for a model newer than
        its own; the checkpoint comes back as bytes (no shared filesystem needed) and the replica's
        service swaps it in as it swaps its own learner's (``Service._take_model``)

So the replicas serve the same models, learnt once, and a replica that starts late takes the newest at
its first poll. When the scene stops, the learner saves ``learned.ckpt`` and ``learned.h5`` in its
``learn_dir`` on the node it ran on.
"""

from __future__ import annotations

import asyncio
import logging
import tempfile
import threading
import time
from pathlib import Path

from edmcgs.server.live.learning import LearnerView

log = logging.getLogger("edmcgs.server.ray")

POLL_S = 1.0
"""How often a render replica asks the scene's learner for a newer model."""
SAVE_TIMEOUT_S = 120.0
"""How long the learner is given to save when the scene stops."""


class SceneLearner:
    """Serve deployment class of a cold-start scene's learner (one replica)."""

    async def __init__(self, name: str, settings: dict, ingest):
        from edmcgs.sensor.buffer.ingest import Ingest
        from edmcgs.server.live.learning import Learning
        from edmcgs.server.ray_serve.shared_source import RemoteSource
        from edmcgs.server.service import learn_config
        from edmcgs.server.settings import Settings

        self.name = name
        self.source = await asyncio.to_thread(RemoteSource, ingest, name)
        info = self.source.info
        config = learn_config(Settings(**settings), info, self.source.extras)
        self.learning = Learning(config, info.width, info.height).start()
        # the stream, as a replica's ingest reads it (reconnecting to a new ingest replica), to the learner
        self.ingest = Ingest(self.source, None, on_batch=self.learning.feed).start()
        log.info("scene %s: learning from the shared stream into %s", name, config.workdir)

    def latest(self, after: int) -> dict:
        """The learner's state, and the newest published model when it is newer than version ``after``
        (its report and checkpoint bytes; None otherwise, or when that file was already replaced)."""
        pub = self.learning.published
        model = None
        if pub is not None and pub["version"] > after:
            try:
                model = (pub, Path(pub["path"]).read_bytes())
            except OSError:  # a newer one replaced it: the next poll takes that
                model = None
        return {"info": self.learning.info(), "model": model}

    def check_health(self) -> None:
        """Serve's probe: a learner that failed is reported on the replicas' /scene, not restarted."""

    def __del__(self):
        ingest = getattr(self, "ingest", None)
        if ingest is not None:
            ingest.stop()
            self.learning.close(SAVE_TIMEOUT_S)


class RemoteLearning(LearnerView):
    """A render replica's view of its scene's ``SceneLearner`` (built as ``Learning`` is: ``Service.open``'s
    ``learning`` factory, with the handle bound)."""

    def __init__(self, handle, config, width: int, height: int, *, poll_s: float = POLL_S):
        super().__init__(config)
        self.handle, self.poll_s = handle, poll_s
        self.remote: dict | None = None
        """The learner's own ``info`` at the last poll."""
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._dir = tempfile.TemporaryDirectory(prefix="edmcgs-learnt-")

    @property
    def running(self) -> bool:
        return bool(self.remote and self.remote["running"])

    def start(self) -> RemoteLearning:
        self.started_unix = time.time()
        self._thread = threading.Thread(target=self._poll, name="edmcgs-learning", daemon=True)
        self._thread.start()
        return self

    def feed(self, batch) -> None:
        """Nothing: the scene's learner reads the shared stream itself."""

    def _poll(self) -> None:
        while not self._stop.wait(self.poll_s):
            after = 0 if self.published is None else self.published["version"]
            try:
                answer = self.handle.latest.remote(after).result(timeout_s=60)
            except Exception as exc:  # Ray's: the learner is restarting or unreachable; asked again next
                self.error = f"the scene's learner did not answer: {type(exc).__name__}"
                continue
            self.remote = answer["info"]
            self.error, self.fed = self.remote["error"], self.remote["fed"]
            if answer["model"] is not None:
                report, data = answer["model"]
                path = Path(self._dir.name) / f"learned-{report['version']:04d}.ckpt"
                path.write_bytes(data)
                self._take(report, path)
                path.unlink(missing_ok=True)

    def info(self) -> dict:
        out = super().info()
        if self.remote is not None:  # where the scene's learner writes, what it saved
            out.update(workdir=self.remote["workdir"], saved=self.remote["saved"],
                       started_unix=self.remote["started_unix"])
        return out

    def close(self, timeout: float = 10.0) -> dict | None:
        """Stop asking (the scene's learner saves when the scene stops)."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout)
        self._dir.cleanup()
        return None
