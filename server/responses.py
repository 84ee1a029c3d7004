"""The JSON bodies of GET /scene and GET /healthz as pydantic models: their schemas in the OpenAPI, and
GET /scene's body checked against them (a key the service adds without adding it here fails loudly in
the tests rather than being left out of the docs). Times follow ``edmcgs.protocol``: ``*_us`` absolute
µs on the checkpoint's clock, ``t*`` seconds from the scene's start.
"""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict

from edmcgs.protocol import TauSource, ValidRange


class _Body(BaseModel):
    model_config = ConfigDict(use_attribute_docstrings=True, extra="forbid")


class Intrinsics(_Body):
    """The render camera's pinhole intrinsics at its native size (pixels)."""

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int


class Size(_Body):
    width: int
    height: int


class Trajectory(_Body):
    """The event camera's poses over the span (the default pose of a render)."""

    t_us: list[int]
    c2w: list[list[float]]
    """Camera-to-world 4x4 matrices, row-major (16 numbers each), OpenCV convention."""


class TrainingViews(_Body):
    """Where the checkpoint's cameras were (``server/views.py``): a view far from all of them shows what
    no training camera saw."""

    center: list[float]
    """The point the training cameras look at (the model's scene centre), world coordinates."""
    scale: float
    """The training cameras' median distance from the centre: the scene's scale."""
    c2w: list[list[float]]
    """The training poses (the trajectory over the span, at most 256 evenly spaced), camera-to-world
    4x4 row-major (16 numbers each)."""


class TauRange(_Body):
    """Where tau(t) comes from over one range of scene time (inclusive bounds)."""

    source: TauSource
    t_min: float
    t_max: float
    t_us_min: int
    t_us_max: int


class OnlineAnchor(_Body):
    t_us: int
    stream_us: int
    """The anchor's time on the stream's clock."""
    corrected: bool
    """Fitted to its frame (else: the event transition's prediction)."""


class FitLoss(_Body):
    before: float
    after: float


class Fit(_Body):
    steps: int
    """Steps of each correction (0: corrections are off)."""
    scale: float
    """Resolution of the correction against the frame (1: full)."""
    colour_lr: float
    """Step size of the colour offsets each correction learns (online appearance; 0: off)."""
    last_s: float | None
    median_s: float | None
    last_loss: FitLoss | None
    """L1 photometric loss of the last correction, before and after its steps."""


class Transition(_Body):
    """What moves the online anchors past the span (server/live/transitions.py)."""

    mode: str
    """select (chosen by the frames), or the one fixed by EDMCGS_ONLINE_TRANSITION."""
    current: str
    """distilled (the checkpoint's online transition), g_phi, or none."""
    evidence: dict[str, float | None]
    """Per candidate, the mean L1 of its predictions of the recent frames (null: none yet)."""


class Online(_Body):
    """Online anchors past the checkpoint's span (predicted by the event transition, then corrected)."""

    span: ValidRange | None
    anchors: list[OnlineAnchor]
    capacity: int
    predicted: int
    corrected: int
    expired: int
    restarted: int
    """Anchors that started the chain again: the events since the one before had left the ring, or
    spanned more than a second (a cold start's model learnt far behind the head)."""
    skipped: dict[str, int]
    """Not corrected, by reason (superseded: a newer frame took the one-slot fit queue)."""
    refused: dict[str, int]
    """Stream frames refused as anchors, by reason."""
    queue_depth: int
    """Online anchors waiting for or in a correction."""
    project: bool
    """Renders of the event camera's view are projected onto the events since their anchor's frame."""
    transition: Transition
    fit: Fit


class HeldOut(_Body):
    """A learnt model's score on frames it was not trained on (the stream's frames between its anchors)."""

    psnr: float
    ssim: float
    ssim_3dgs: float | None = None
    frames: int


class LearntModel(_Body):
    """The model a cold start's learner published last, served since ``live_unix``."""

    version: int
    """1 for the first model, then one more per publication."""
    span_us: list[int]
    """The scene times it learnt: its first anchor and its span's end."""
    anchors: int
    steps: int
    """Training steps behind it (this round's)."""
    gaussians: int
    cpu_s: float
    """The learner's CPU seconds when it was published."""
    preset: str
    """The config it trained (``auto`` resolved: ``moving`` or ``real``)."""
    camera: str
    """How its camera poses are known: ``stated`` (by the stream), ``estimated: moving`` (``turning``,
    ``still``: structure from motion over its anchor frames), or ``still`` (assumed)."""
    heldout: HeldOut | None
    """Null: the stream has no frame between its anchors yet."""
    live_unix: float
    """When the server swapped it in (Unix seconds)."""


class Learning(_Body):
    """A cold start's learner (``edmcgs-serve --replay REC`` or ``--live`` without a checkpoint)."""

    workdir: str
    """Where it writes its checkpoints; on stop ``learned.ckpt`` (resumable) and ``learned.h5``."""
    preset: str
    """The config asked for (``auto``: ``moving`` for a camera that translates, else ``real``)."""
    anchor_fps: float
    running: bool
    error: str | None
    fed: dict[str, int]
    """What the server has given it: batches, events, frames."""
    version: int | None
    """The model served now (null: none learnt yet: renders are the stream's frames moved by the
    events)."""
    model: LearntModel | None
    started_unix: float | None
    saved: dict | None
    """What it saved when it stopped."""


class Source(_Body):
    """The event source."""

    sensor: str
    live: bool
    width: int
    height: int
    has_frames: bool
    loop: bool
    speed: float | None
    """Replay speed (real-time factor); null for a live camera."""
    period_us: int | None
    """A looping replay's period on the stream clock (null: no loop, or the clock is not known yet)."""


class Playback(_Body):
    """Without a sensor: the clock that moves the head over the span, in a loop."""

    speed: float
    period_us: int
    loop: bool


class Limits(_Body):
    max_width: int
    max_height: int
    stream_max_fps: float


class Scene(_Body):
    """What the service serves: span, anchors, camera, trajectory and what can be rendered now."""

    t_start_us: int
    """The scene's start (its first anchor); ``t`` counts seconds from it."""
    t_end_us: int
    duration_s: float
    anchors_us: list[int]
    """The checkpoint's anchors: the frames it was trained on."""
    intrinsics: Intrinsics
    event_size: Size
    """The event camera's sensor size."""
    trajectory: Trajectory | None
    channels: int
    """1 (grey) or 3 (RGB)."""
    has_event_branch: bool
    num_gaussians: int
    head_us: int | None
    """The live head: the newest time whose events have all arrived (null: none yet)."""
    head_t: float | None
    stream_head_us: int | None
    """The head on the stream's clock."""
    renderable: ValidRange | None
    """The most recent interval GET /render accepts now."""
    renderable_ranges: list[ValidRange]
    """Every interval GET /render accepts now, oldest first."""
    tau_sources: list[TauRange]
    """Where tau(t), the anchor of each render's events window [tau, t), comes from: within the
    checkpoint's span its own anchors (checkpoint), where it has none the stream's frames (stream), past
    its end online anchors (online)."""
    training_views: TrainingViews | None
    """The training cameras (null: the checkpoint has no trajectory)."""
    online: Online | None
    learning: Learning | None
    """A cold start's learner (null: the checkpoint was given)."""
    source: Source | None
    playback: Playback | None
    limits: Limits
    formats: list[Literal["png", "jpeg", "msgpack"]]
    """GET /render's formats."""
    stream_formats: list[Literal["jpeg", "png", "raw"]]
    """The websocket's frame formats."""
    render_modes: list[Literal["rgb", "depth", "alpha"]]
    """What a render can show (GET /render's ``mode``, a subscription's ``render_mode``): the colour, the
    expected camera z as grey, the splats' accumulated opacity as grey."""


class Health(_Body):
    """GET /healthz: ready when the model is loaded and the source delivers (no sensor: once loaded)."""

    ready: bool
    model: Literal["loaded", "learning"]
    """learning: a cold start before its first model."""
    device: str
    source: Literal["none", "streaming", "ended", "stopped", "error"]
    source_error: str | None
    events_in_ring: int
    head_us: int | None
    uptime_s: float
