"""Service settings: environment variables with the ``EDMCGS_`` prefix, overridden by CLI flags.

Built by the app factory (or the CLI), never at import time.
"""

from __future__ import annotations

from pathlib import Path
from typing import Literal

from pydantic import Field, SecretStr, field_validator, model_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

from edmcgs.protocol import TRANSITIONS
from edmcgs.server.live.config import LearnConfig, OnlineConfig

LOOPBACK = ("127.0.0.1", "localhost", "::1")
RING_BYTES_PER_EVENT = 13
"""t int64, x and y uint16, p int8: the ring's arrays (sensor/buffer/ring.py)."""
ONLINE = OnlineConfig()
"""The online anchors' defaults (live/config.py: their one place)."""
LEARN = LearnConfig()
"""A cold start's learner's defaults (live/config.py)."""


def host_allowlist(host: str, allowed_hosts: list[str] | None) -> list[str] | None:
    """The Host / Origin names a server bound to ``host`` accepts (None: any): ``allowed_hosts`` when
    given, else the loopback names on a loopback bind, any name otherwise."""
    if allowed_hosts is not None:
        return allowed_hosts
    return list(LOOPBACK) if host in LOOPBACK else None


def _memory_bytes() -> int:
    """Physical memory of the machine (or its cgroup limit when lower)."""
    import os

    total = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    try:
        with open("/sys/fs/cgroup/memory.max") as f:
            limit = f.read().strip()
        if limit.isdigit():
            total = min(total, int(limit))
    except OSError:
        pass
    return total


class Settings(BaseSettings):
    """Everything ``edmcgs-serve`` can be told. Each field is also ``EDMCGS_<NAME>`` in the environment."""

    model_config = SettingsConfigDict(env_prefix="EDMCGS_", extra="forbid")

    checkpoint: Path | None = Field(None, description="EdMCGS checkpoint to serve; none with --replay or "
                                    "--live: learn one from the stream while serving (a cold start); none "
                                    "at all: the bundled demo's.")
    replay: Path | None = Field(None, description="Recording to replay (any format the sensor layer reads); "
                                                  "none with no --live: the bundled demo's recording, or, "
                                                  "with a checkpoint without an event branch, no sensor.")
    live: bool = Field(False, description="Read a DAVIS346 over USB instead of replaying a file.")
    speed: float = Field(1.0, gt=0, le=1e6,
        description="Replay speed, a real-time factor (without a sensor: the "
                                                 "speed of the clock playing the span).")
    loop: bool = Field(False, description="Start the replay over at its end (the demo always loops).")
    host: str = Field("127.0.0.1", description="Interface to bind; loopback unless told otherwise.")
    port: int = Field(8000, ge=0, le=65535, description="TCP port (0: any free port).")
    device: str = Field("cpu", description="Torch device of the model: 'cpu', 'cuda', 'cuda:1' ...")
    token: SecretStr | None = Field(None, description="When set, every route and the websocket require "
                                                      "'Authorization: Bearer <token>'.")
    allowed_hosts: list[str] | None = Field(None, description="Host names the service answers to (Host "
                                            "header; a websocket's or a browser's Origin too): a DNS-"
                                            "rebinding page or another site's websocket is refused. None: "
                                            "the loopback names when bound to loopback, any host otherwise; "
                                            "['*']: any.")
    open_probes: bool = Field(False, description="Serve /healthz and /metrics without the token (for "
                                                  "probes and scrapers); every other route still wants it.")
    max_width: int = Field(1920, gt=0, le=16_384, description="Largest width a client may ask for (px).")
    max_height: int = Field(1920, gt=0, le=16_384, description="Largest height a client may ask for (px).")
    render_workers: int = Field(2, gt=0, le=256,
        description="Renders running at once (threads of the render pool).")
    render_queue: int = Field(8, ge=0, le=100_000,
        description="Renders waiting for a worker before GET /render "
                                                   "answers 503 with Retry-After.")
    stream_workers: int = Field(1, gt=0, le=64, description="Threads rendering websocket frames, shared by "
                                "every stream and apart from GET /render's workers and queue (a stream "
                                "never takes a single render's slot).")
    max_streams: int = Field(16, ge=0, le=10_000, description="Open websocket streams at most; one more is "
                             "answered with an error message and close code 1013 (try again later).")
    max_connections: int = Field(256, gt=0, le=100_000, description="Requests and websockets in progress "
                                 "at most; beyond it HTTP answers 503 busy, a websocket is closed with 1013. "
                                 "Connections that have not sent a request do not count.")
    head_timeout_s: float = Field(10.0, gt=0, le=3600, description="Seconds a connection has to send a "
                                  "request's line and headers, from its opening (or the request's first "
                                  "byte after a response); past them it is closed (an idle or half-sent "
                                  "connection holds nothing).")
    stream_max_fps: float = Field(60.0, gt=0, le=1000,
        description="Highest frame rate one websocket may ask for.")
    replay_batch_us: int = Field(5_000, gt=0, le=10_000_000,
        description="Recording time per replay batch pushed to the "
                                                          "ring (µs): the latency a replay adds.")
    ring_events: int = Field(4_000_000, gt=0, description="Capacity of the event ring buffer (events).")
    deform_cache: int = Field(32, ge=1, le=4096,
        description="Deformed Gaussian states kept, keyed by (t, anchor, "
                                                    "event count), shared by every client.")
    jpeg_quality: int = Field(90, ge=1, le=100, description="JPEG quality of rendered frames.")
    png_compress_level: int = Field(1, ge=0, le=9, description="zlib level of PNG frames (1: fast).")
    torch_threads: int | None = Field(1, gt=0, le=1024,
        description="torch intra-op threads (the deformation); 1: "
                                                         "renders run side by side on the pool instead, "
                                                         "and a parallel region never waits on a core "
                                                         "another process holds; none: torch's own.")
    online_anchors: int = Field(ONLINE.capacity, gt=0, le=100_000,
        description="Online anchors kept past the checkpoint's span (the stream's frames, predicted and "
                    "corrected); older ones also expire with their events.")
    online_fit_steps: int = Field(ONLINE.fit_steps, ge=0, le=10_000,
        description="Optimisation steps correcting each online anchor against its frame, in a background "
                    "thread (0: predictions only).")
    online_fit_lr: float = Field(ONLINE.fit_lr, gt=0, le=1,
        description="Adam step size of that correction, as a fraction of the scene's extent.")
    online_transition: Literal[TRANSITIONS] = Field(ONLINE.transition,
        description="What moves online anchors past the span: select (default): of g_phi, the "
                    "checkpoint's distilled transition (edmcgs distill) and none, the one whose predictions "
                    "of the recent frames were best; or that one, fixed.")
    online_finetune_steps: int = Field(ONLINE.finetune_steps, ge=0, le=10_000,
        description="After each correction, Adam steps letting a copy of g_phi (the event transition) "
                    "learn from it, for the predictions past the span only (0: g_phi stays as trained).")
    online_finetune_lr: float = Field(ONLINE.finetune_lr, gt=0, le=1,
        description="Adam step size of that fine-tune.")
    online_spawn: int = Field(ONLINE.spawn, ge=0, le=100_000,
        description="For a checkpoint drawn in anchor windows (the real preset): at most this many static "
        "Gaussians added at each corrected online anchor where its frame differs from the render (what "
        "entered the view since the checkpoint's last window); 0 (default): none, as they ghost once what "
        "they show moves on (reports/online-traffic.md).")
    online_colour_lr: float = Field(ONLINE.colour_lr, ge=0, le=1,
        description="Step size of the per-Gaussian colour offsets each correction learns beside the motion "
                    "(online appearance: what the frames show that the checkpoint never saw, such as views "
                    "past the training ones); they carry from anchor to anchor. 0: the checkpoint's colours "
                    "(reports/online.md).")
    online_fit_scale: float = Field(ONLINE.fit_scale, gt=0, le=1,
        description="Fraction of the frame's size the correction renders and compares at.")
    online_project: bool = Field(ONLINE.project,
        description="Renders of the event camera's own view (no pose given, or its own) from an online "
                    "anchor are clipped into the bounds its frame and the events since it put on each "
                    "pixel: one contrast threshold either side of the frame moved by the events "
                    "(model/online/bounds.py). The model renders what the events leave open. Off: the "
                    "model's render alone.")
    intrinsics: str | None = Field(None, description="A cold start's camera: fx,fy,cx,cy in pixels, or a DV "
                                   "calibration file (default: what the recording states, else fx = fy = "
                                   "width, centred).")
    frames_kept: int = Field(1024, gt=0, le=1_000_000, description="A cold start's stream frames kept for "
                             "renders and online anchors (the oldest go first; at 25 Hz, 41 s).")
    learn_dir: Path = Field(LEARN.workdir, description="Where a cold start's learner writes the checkpoints "
                            "it publishes, and on stop learned.ckpt (resumable) and learned.h5 (the stream).")
    learn_preset: str = Field(LEARN.preset, description="The config a cold start's learner trains (edmcgs "
                              "train --config); auto: moving for a camera that translates, else real.")
    learn_poses: Literal["auto", "static"] = Field(LEARN.poses, description="With no poses stated: auto, "
                                                   "structure from motion over each round's anchor frames "
                                                   "(edmcgs poses); static, the camera taken as still.")
    learn_set: list[str] = Field(list(LEARN.overrides), description="key=value changes to that config "
                                 "(edmcgs train --set; EDMCGS_LEARN_SET is a JSON list).")
    learn_anchor_fps: float = Field(LEARN.anchor_fps, gt=0, le=1000, description="Frames at this rate are "
                                    "the learner's anchors; the others are held out and scored.")
    learn_first_steps: int = Field(LEARN.first_steps, gt=0, le=1_000_000, description="Steps of the "
                                   "learner's first round (then twice the last, up to the preset's).")
    learn_publish_s: float = Field(LEARN.publish_s, gt=0, le=86_400, description="Seconds between two "
                                   "checkpoints the learner publishes within a round (each round's end "
                                   "publishes one too).")
    raster_threads: int | None = Field(None, gt=0, le=1024,
        description="Threads of the numba rasterizer per render; "
                                       "none: every core (on a 2-core CPU, 2 per render beat 1 at one and at "
                                       "four clients: bench.serve render p50 20 vs 27 ms), or beside a cold "
                                       "start's learner the cores it leaves.")

    @field_validator("device")
    @classmethod
    def _device_available(cls, value: str) -> str:
        from edmcgs.errors import InvalidInputError
        from edmcgs.model.devices import check_device

        try:
            return check_device(value)
        except InvalidInputError as exc:
            raise ValueError(str(exc)) from None

    @field_validator("ring_events")
    @classmethod
    def _ring_fits(cls, value: int) -> int:
        need = value * RING_BYTES_PER_EVENT
        budget = _memory_bytes() // 4
        if need > budget:
            raise ValueError(f"a ring of {value} events needs {need / 2**30:.1f} GiB, more than a quarter "
                             f"of this machine's memory ({budget / 2**30:.1f} GiB); at most "
                             f"{budget // RING_BYTES_PER_EVENT} events")
        return value

    @model_validator(mode="after")
    def _one_source(self) -> Settings:
        if self.live and self.replay is not None:
            raise ValueError("replay and live are exclusive: give one event source")
        return self  # a checkpoint alone: Service.open checks that it has no event branch

    @property
    def online(self) -> OnlineConfig:
        """The online anchors' configuration these settings give (live/config.py)."""
        return OnlineConfig(capacity=self.online_anchors, fit_steps=self.online_fit_steps,
                            fit_lr=self.online_fit_lr, fit_scale=self.online_fit_scale,
                            colour_lr=self.online_colour_lr, transition=self.online_transition,
                            finetune_steps=self.online_finetune_steps, finetune_lr=self.online_finetune_lr,
                            spawn=self.online_spawn, project=self.online_project)

    @property
    def host_allowlist(self) -> list[str] | None:
        """The Host / Origin names to accept (None: any)."""
        return host_allowlist(self.host, self.allowed_hosts)

    @property
    def uses_demo(self) -> bool:
        """True when neither a checkpoint nor a source is given: serve the bundled demo scene."""
        return self.checkpoint is None and self.replay is None and not self.live

    @property
    def learning(self) -> bool:
        """True when a source is given without a checkpoint: learn the model while serving."""
        return self.checkpoint is None and (self.replay is not None or self.live)

    @property
    def sensorless(self) -> bool:
        """True when a checkpoint is given without a source: a scene without events, served alone."""
        return self.checkpoint is not None and self.replay is None and not self.live
