"""The wire schema of the edmcgs service, shared by the server and every client.

This module imports nothing of the project (clients depend on it alone) and nothing heavier than
msgpack. It fixes the names on the wire; the server validates with it and clients build with it.

Time on the wire
    ``t`` is seconds (float) from the scene's start, ``t_us`` is absolute microseconds (int, the time
    base of the checkpoint and its recording; Unix-epoch µs for real cameras). ``t_us = t_start_us +
    round(t * 1e6)``. Every response carries both.

HTTP ``GET /render``
    Query: ``t`` | ``t_us`` (neither: the live head), ``pose`` (16 numbers row-major camera-to-world,
    or 7 numbers ``tx,ty,tz,qw,qx,qy,qz``, comma-separated or a JSON array; absent: the event
    camera's own pose at t), ``width``, ``height`` (one alone keeps the aspect ratio), ``format``
    (``png`` | ``jpeg`` | ``msgpack``; absent: negotiated from ``Accept``, default png), ``mode``
    (``RENDER_MODES``: ``rgb``, the default; ``depth``, the expected camera z of each pixel, grey:
    ``DEPTH_GREY_NEAR``; ``alpha``, the splats' accumulated opacity 1 - T, grey). The headers ``HEADERS``
    describe the render (``FrameMeta.headers`` / ``from_headers``). ``msgpack`` bodies are a frame map
    (below) without ``seq`` and ``dropped``.

Poses on the wire
    Camera-to-world, OpenCV convention (x right, y down, z forward), in one of two forms: 16 numbers,
    the 4x4 matrix row-major; or 7, ``tx,ty,tz,qw,qx,qy,qz``: the quaternion's w FIRST. (TUM trajectory
    files, which ``--poses`` reads, put it last: ``t tx ty tz qx qy qz qw``.)

HTTP ``GET /scene``
    A JSON map of the scene (span, anchors, camera, trajectory, what can be rendered now). Its
    ``tau_sources`` says where tau(t), the anchor of each render (``anchor_us``), comes from: a list,
    in time order, of maps ``{"source": <TauSource>, "t_min", "t_max", "t_us_min", "t_us_max"}``
    (``TAU_SOURCE_KEYS``; inclusive bounds). Within the checkpoint's span its own anchors rule
    (``"checkpoint"``: the windows it was trained on, however many frames the stream carries); a
    stream's frames (``"stream"``) only where the checkpoint has no anchor.

HTTP ``GET /ply``
    Query: ``t`` | ``t_us`` as ``GET /render``. The body is the deformed Gaussians at that instant as a
    3DGS PLY file (an attachment); the headers ``HEADER_T_US``, ``HEADER_T``, ``HEADER_ANCHOR_US``,
    ``HEADER_EVENTS`` and ``HEADER_ANCHOR`` describe the instant.

HTTP ``GET /events``
    The event map I_E of the window a render at the same time uses (``[tau(t), t)``, the events the
    model's event branch sees): query ``t`` | ``t_us`` as for ``/render`` (the same time rules and
    errors), ``format`` (``EVENT_FORMATS``; absent: from ``Accept``, default png). ``png``: an RGBA
    picture at the event sensor's size, DV-style: ``EVENT_ON_RGB`` where the window's signed polarity
    sum is positive, ``EVENT_OFF_RGB`` where it is negative, transparent where it is zero (draw it
    over a render or on white). ``msgpack``: an event-map map (``EVENT_MAP_KEYS``) whose ``data`` is
    the signed sum itself, ``EVENT_MAP_DTYPE`` [height, width] row-major. The headers
    ``EVENT_HEADERS`` describe the window (``EventMapMeta``).

Websocket ``/stream``
    Client -> server: a subscription map (msgpack binary or JSON text), see ``Subscription``. It may
    be re-sent at any time, whole or in part (e.g. only ``{"pose": [...]}``); the fields sent replace
    the current ones. Server -> client messages are msgpack maps with a ``type``:
    ``"subscribed"`` (the subscription in force), ``"frame"`` (``FRAME_KEYS``), ``"error"``
    (``ERROR_KEYS``; the connection stays open and the previous subscription stays in force) and
    ``"end"`` (a sweep without ``loop`` is done). A client that reads slowly gets the newest frame:
    older unsent frames are dropped and counted in ``dropped``.

Errors (HTTP bodies and websocket ``error`` messages)
    JSON / msgpack map ``{"error": <ErrorCode>, "detail": <message>, "param": <name or null>,
    "valid_range": {"t_min", "t_max", "t_us_min", "t_us_max"} or null}`` (``ErrorBody``). Each code has
    one HTTP status (``STATUS``): 401 unauthorized, 416 time_unavailable (``valid_range`` says what
    can be rendered), 422 invalid_input (``param`` names it), 503 busy (``Retry-After`` header) or
    not_ready, 500 render_failed.
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass, field, fields
from enum import StrEnum
from typing import Any, Literal

import msgpack
from typing_extensions import TypedDict  # not typing's: schema generators read it on Python 3.11 too


def t_us_of_seconds(t: float, t_start_us: int) -> int:
    """Seconds from the scene's start -> absolute µs: ``t_start_us + round(t * 1e6)``."""
    return int(t_start_us) + round(t * 1e6)


def seconds_of(t_us: int, t_start_us: int) -> float:
    """Absolute µs -> seconds from the scene's start."""
    return (int(t_us) - int(t_start_us)) / 1e6


# --- HTTP ---------------------------------------------------------------------------------------

HEADER_T_US = "X-Edmcgs-T-Us"  # absolute µs actually rendered (int)
HEADER_T = "X-Edmcgs-T"  # the same, seconds from the scene's start (float)
HEADER_ANCHOR_US = "X-Edmcgs-Anchor-Us"  # tau(t): the anchor frame whose events window was used (int µs)
HEADER_EVENTS = "X-Edmcgs-Events"  # number of events in the half-open window [tau(t), t) (int)
HEADER_RENDER_MS = "X-Edmcgs-Render-Ms"  # server time spent on the render, encoding included (float)
HEADER_WIDTH = "X-Edmcgs-Width"  # image width, px
HEADER_HEIGHT = "X-Edmcgs-Height"  # image height, px
HEADER_CHANNELS = "X-Edmcgs-Channels"  # 1 (grey) or 3 (RGB)
HEADER_ANCHOR = "X-Edmcgs-Anchor"  # what the anchor is: checkpoint | predicted | corrected | frame
HEADER_PROJECTED = "X-Edmcgs-Projected"  # true | false: projected onto the events since the anchor's frame
HEADER_MODE = "X-Edmcgs-Mode"  # what the pixels are: rgb | depth | alpha (RENDER_MODES)
HEADER_DEPTH_NEAR = "X-Edmcgs-Depth-Near"  # depth mode: the camera z (m) grey 255 stands for; else absent
HEADER_DEPTH_FAR = "X-Edmcgs-Depth-Far"  # depth mode: the camera z (m) grey 1 stands for; else absent
HEADER_MODEL = "X-Edmcgs-Model"  # the model that rendered: 0 the given checkpoint, n the n-th learnt, none
HEADERS = (HEADER_T_US, HEADER_T, HEADER_ANCHOR_US, HEADER_EVENTS, HEADER_RENDER_MS, HEADER_WIDTH,
           HEADER_HEIGHT, HEADER_CHANNELS, HEADER_ANCHOR, HEADER_PROJECTED, HEADER_MODE, HEADER_MODEL)
"""The headers of every GET /render response (a depth render adds ``HEADER_DEPTH_NEAR`` / ``_FAR``)."""

RENDER_MODES = ("rgb", "depth", "alpha")
"""What a render's pixels show: the colour; the expected depth along the camera's z of each pixel,
sum_i w_i z_i / sum_i w_i over the splats blended into it (w_i = alpha_i T_i; normalised by the pixel's
opacity, so a faint edge has its surface's depth), grey (``DEPTH_GREY_NEAR``); the accumulated opacity
of the splats 1 - T (T the transmittance left behind the last one), grey 0..255. Depth and alpha leave
out a checkpoint's background layer (not Gaussians) and are never projected onto the events."""

DEPTH_GREY_NEAR = 255
"""A depth render's grey at its near (``HEADER_DEPTH_NEAR``, the frame map's ``depth_near``)."""
DEPTH_GREY_FAR = 1
"""... at its far (``HEADER_DEPTH_FAR``, ``depth_far``); linear in camera z between, depths beyond clipped:
z = far - (grey - 1) / 254 * (far - near)."""
DEPTH_GREY_NONE = 0
"""... where the splats cover less than ``DEPTH_MIN_ALPHA`` of the pixel (nothing solid there)."""
DEPTH_MIN_ALPHA = 0.5
"""A depth render shows a pixel's depth where the splats' accumulated opacity reaches this: a faint haze
of splats has a depth, but no surface to see; the near / far percentiles are of these pixels."""

RENDER_FORMATS = ("png", "jpeg", "msgpack")
STREAM_FORMATS = ("jpeg", "png", "raw")
MEDIA_TYPES = {"png": "image/png", "jpeg": "image/jpeg", "msgpack": "application/msgpack"}
# Accept values recognised for negotiation, in addition to MEDIA_TYPES' values.
ACCEPT_ALIASES = {"image/jpg": "jpeg", "application/x-msgpack": "msgpack",
                  "application/vnd.msgpack": "msgpack"}

STREAM_MODES = ("live", "sweep")

# Keys of a frame map (websocket "frame" message; the msgpack body of /render without STREAM_KEYS).
FRAME_KEYS = (
    "type",  # "frame"
    "seq",  # frame number on this connection, from 0; a gap is a dropped frame
    "dropped",  # frames dropped on this connection so far (the client was slower than the frame rate)
    "t_us",  # absolute µs rendered
    "t",  # seconds from the scene's start
    "anchor_us",  # tau(t) in absolute µs
    "events",  # events in the half-open window [tau(t), t)
    "render_ms",  # server time of the render and its encoding
    "arrived_unix_us",  # live mode: Unix µs at which the oldest event new to this frame reached the ring
    "head_arrived_unix_us",  # live mode: Unix µs at which the batch that brought the frame's time arrived
    "width",
    "height",
    "channels",  # 1 (grey) or 3 (RGB)
    "format",  # "jpeg" | "png" | "raw" (msgpack body of /render: "raw")
    "anchor",  # what the anchor is: "checkpoint" | "predicted" | "corrected" | "frame" (ANCHOR_KINDS)
    "projected",  # true: the event camera's view projected onto the events since the anchor's frame
    "render_mode",  # what the pixels show: "rgb" | "depth" | "alpha" (RENDER_MODES)
    "depth_near",  # depth: the camera z (m) grey 255 stands for (DEPTH_GREY_NEAR); else null
    "depth_far",  # depth: the camera z (m) grey 1 stands for; else null
    "model_version",  # the model that rendered: 0 the given checkpoint, n the n-th learnt; null: none yet
    "data",  # bytes: the encoded image, or for "raw" uint8 pixels [height, width, channels] row-major
)
LIVE_KEYS = ("arrived_unix_us", "head_arrived_unix_us")
"""Frame keys only a live stream's frames carry."""
STREAM_KEYS = ("seq", "dropped", *LIVE_KEYS)
"""Frame keys a websocket adds to a render's (``FrameMeta.to_message``'s ``stream``)."""
ERROR_KEYS = ("type", "error", "detail", "param", "valid_range")


class ProtocolError(ValueError):
    """A message does not follow this schema; ``param`` names the offending field."""

    def __init__(self, param: str | None, detail: str):
        super().__init__(detail)
        self.param = param
        self.detail = detail


MAX_POSE_TEXT = 4096
"""Longest ``pose`` query value (characters): 16 numbers at full float64 precision take about 400."""


def json_depth(text: str) -> int:
    """How deeply the arrays and objects of JSON ``text`` nest, counted without parsing it (so that a
    deeply nested input is refused before the recursive parser sees it); brackets inside strings are
    skipped."""
    depth = deepest = 0
    in_string = escaped = False
    for ch in text:
        if in_string:
            if escaped:
                escaped = False
            elif ch == "\\":
                escaped = True
            elif ch == '"':
                in_string = False
        elif ch == '"':
            in_string = True
        elif ch in "[{":
            depth += 1
            deepest = max(deepest, depth)
        elif ch in "]}":
            depth -= 1
    return deepest


def parse_pose_text(text: str) -> list[float]:
    """Parse the ``pose`` query value: numbers separated by commas (or a JSON array) -> list of floats.

    Only the syntax is checked here (16 or 7 finite numbers); the server checks the geometry.
    """
    raw = text.strip()
    if len(raw) > MAX_POSE_TEXT:
        raise ProtocolError("pose", f"pose is {len(raw)} characters long; 16 numbers fit in {MAX_POSE_TEXT}")
    if raw.startswith("["):
        if json_depth(raw) > 2:
            raise ProtocolError("pose", "pose must be a flat JSON array of 16 or 7 numbers, or a 4x4 "
                                        "nested one (nested deeper than 2)")
        try:
            values = json.loads(raw)
        except ValueError as exc:
            raise ProtocolError("pose", f"pose is not a valid JSON array: {exc}") from None
    else:
        values = [v for v in raw.replace(";", ",").split(",") if v.strip()]
    return check_pose_numbers(values)


def check_pose_numbers(values: Any) -> list[float]:
    """Check a pose given as a sequence of 16 (row-major c2w) or 7 (tx,ty,tz,qw,qx,qy,qz: w first)
    numbers."""
    if isinstance(values, (str, bytes)) or not hasattr(values, "__len__"):
        raise ProtocolError("pose", "pose must be a list of 16 or 7 numbers")
    if len(values) == 4 and all(hasattr(row, "__len__") and len(row) == 4 for row in values):
        values = [v for row in values for v in row]  # a nested 4x4 matrix
    if len(values) not in (16, 7):
        raise ProtocolError("pose", f"pose must have 16 (4x4 row-major c2w) or 7 (tx,ty,tz,qw,qx,qy,qz: the "
                                    f"quaternion's w first) numbers, got {len(values)}")
    out = []
    for i, v in enumerate(values):
        try:
            f = float(v)
        except (TypeError, ValueError):
            raise ProtocolError("pose", f"pose[{i}] is not a number: {v!r}") from None
        if not math.isfinite(f):
            raise ProtocolError("pose", f"pose[{i}] is not finite: {v!r}")
        out.append(f)
    return out


def negotiate_format(accept: str | None) -> str:
    """The render format asked for by an ``Accept`` header (q-values honoured); ``png`` by default."""
    if not accept:
        return "png"
    by_type = {media: name for name, media in MEDIA_TYPES.items()} | ACCEPT_ALIASES
    best, best_q = "png", -1.0
    for order, part in enumerate(accept.split(",")):
        media, *params = (p.strip() for p in part.split(";"))
        q = 1.0
        for p in params:
            if p.startswith("q="):
                try:
                    q = float(p[2:])
                except ValueError:
                    q = 0.0
        name = by_type.get(media.lower())
        # Earlier entries win ties; q=0 means "not acceptable".
        if name is not None and q > 0 and q - order * 1e-9 > best_q:
            best, best_q = name, q - order * 1e-9
    return best


# --- websocket ----------------------------------------------------------------------------------

@dataclass
class Subscription:
    """What a websocket client asks the server to push (each field's docstring says what it means)."""

    mode: Literal["live", "sweep"] = "live"
    """``"live"`` follows the head of the event stream; ``"sweep"`` runs t0..t1 in scene time."""
    t0: float | None = None
    """Sweep start in seconds from the scene's start (``None``: the scene's start)."""
    t1: float | None = None
    """Sweep end in seconds from the scene's start (``None``: the scene's end)."""
    t0_us: int | None = None
    """Sweep start in absolute µs (takes precedence over t0)."""
    t1_us: int | None = None
    """Sweep end in absolute µs (takes precedence over t1)."""
    fps: float = 30.0
    """Frames per second pushed (live: at most; the server caps it)."""
    speed: float = 1.0
    """Sweep only: scene seconds per wall second (1.0 = real time)."""
    loop: bool = False
    """Sweep only: start over at t1 instead of ending."""
    pose: list[float] | None = None
    """Camera-to-world, OpenCV convention: 16 numbers (the 4x4 row-major) or 7 (tx,ty,tz,qw,qx,qy,qz: the
    quaternion's w first, where TUM files put it last), or a nested 4x4 (see ``check_pose_numbers``);
    ``None``: the event camera's own pose."""
    width: int | None = None
    """Output width in pixels (``None``: the event camera's; one side alone keeps the aspect ratio)."""
    height: int | None = None
    """Output height in pixels (``None``: the event camera's; one side alone keeps the aspect ratio)."""
    format: Literal["jpeg", "png", "raw"] = "jpeg"
    """``"jpeg"`` | ``"png"`` | ``"raw"`` (uint8 pixels [height, width, channels], row-major)."""
    render_mode: Literal["rgb", "depth", "alpha"] = "rgb"
    """What the frames show (``RENDER_MODES``; GET /render's ``mode``): ``"rgb"``, ``"depth"`` (the expected
    camera z, grey: 255 at the frame's ``depth_near``, 1 at its ``depth_far``, 0 where the splats' opacity
    is below ``DEPTH_MIN_ALPHA``) or
    ``"alpha"`` (the splats' accumulated opacity, grey)."""

    def to_message(self) -> dict:
        """The map to send (``None`` fields left out)."""
        return {k: v for k, v in asdict(self).items() if v is not None}

    def updated(self, message: dict) -> Subscription:
        """A copy with the fields of ``message`` applied, validated; raises ProtocolError."""
        if not isinstance(message, dict):
            raise ProtocolError(None, "a subscription must be a map (msgpack map or JSON object)")
        if not all(isinstance(k, str) for k in message):
            raise ProtocolError(None, "subscription field names must be strings")
        known = {f.name for f in fields(self)}
        unknown = sorted(set(message) - known)
        if unknown:
            raise ProtocolError(unknown[0], f"unknown subscription field {unknown[0]!r}; "
                                            f"known: {', '.join(sorted(known))}")
        values = asdict(self) | message
        return _validated(values)


LIMITS = {"t0": 1e9, "t1": 1e9, "t0_us": 2**62, "t1_us": 2**62, "fps": 1e4, "speed": 1e6,
          "width": 2**20, "height": 2**20}
"""Largest magnitude of each numeric subscription field: beyond any clock or image (the server's own
limits are tighter); a value past it is refused before any arithmetic can overflow."""
MAX_MESSAGE_BYTES = 64 * 1024
"""Largest websocket message the server parses (a subscription is a few hundred bytes)."""
MAX_MESSAGE_DEPTH = 4
"""Deepest nesting of a websocket message (a subscription's 4x4 pose is 3 deep)."""


def _number(values: dict, name: str, *, integer: bool = False, positive: bool = False,
            optional: bool = True) -> Any:
    v = values[name]
    if v is None:
        if optional:
            return None
        raise ProtocolError(name, f"{name} is required")
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise ProtocolError(name, f"{name} must be a number, got {type(v).__name__}")
    limit = LIMITS.get(name, 2**62)
    if isinstance(v, int) and abs(v) > limit:
        raise ProtocolError(name, f"{name} is out of range (|{name}| <= {limit:g})")
    if not math.isfinite(v):
        raise ProtocolError(name, f"{name} must be finite, got {v!r}")
    if abs(v) > limit:
        raise ProtocolError(name, f"{name}={v:g} is out of range (|{name}| <= {limit:g})")
    if integer:
        if float(v) != int(v):
            raise ProtocolError(name, f"{name} must be an integer, got {v!r}")
        v = int(v)
    if positive and v <= 0:
        raise ProtocolError(name, f"{name} must be > 0, got {v!r}")
    return v


def _validated(values: dict) -> Subscription:
    if values["mode"] not in STREAM_MODES:
        raise ProtocolError("mode", f"mode must be one of {STREAM_MODES}, got {values['mode']!r}")
    if values["format"] not in STREAM_FORMATS:
        raise ProtocolError("format", f"format must be one of {STREAM_FORMATS}, got {values['format']!r}")
    if values["render_mode"] not in RENDER_MODES:
        raise ProtocolError("render_mode", f"render_mode must be one of {RENDER_MODES}, got "
                                           f"{values['render_mode']!r}")
    if not isinstance(values["loop"], bool):
        raise ProtocolError("loop", f"loop must be true or false, got {values['loop']!r}")
    out = dict(
        mode=values["mode"], format=values["format"], loop=values["loop"], render_mode=values["render_mode"],
        t0=_number(values, "t0"), t1=_number(values, "t1"),
        t0_us=_number(values, "t0_us", integer=True), t1_us=_number(values, "t1_us", integer=True),
        fps=_number(values, "fps", positive=True, optional=False),
        speed=_number(values, "speed", positive=True, optional=False),
        width=_number(values, "width", integer=True, positive=True),
        height=_number(values, "height", integer=True, positive=True),
        pose=None if values["pose"] is None else check_pose_numbers(values["pose"]),
    )
    return Subscription(**out)


def decode_message(data: bytes | str) -> Any:
    """A websocket message: msgpack when binary, JSON when text; raises ProtocolError."""
    if data is None or len(data) > MAX_MESSAGE_BYTES:
        raise ProtocolError(None, f"message is empty or longer than {MAX_MESSAGE_BYTES} bytes")
    try:
        if isinstance(data, str):
            if json_depth(data) > MAX_MESSAGE_DEPTH:
                raise ProtocolError(None, f"message nests deeper than {MAX_MESSAGE_DEPTH}")
            return json.loads(data)
        message = msgpack.unpackb(data, raw=False)
        if _depth(message, MAX_MESSAGE_DEPTH + 1) > MAX_MESSAGE_DEPTH:
            raise ProtocolError(None, f"message nests deeper than {MAX_MESSAGE_DEPTH}")
        return message
    except (ValueError, TypeError, RecursionError, msgpack.ExtraData, msgpack.FormatError,
            msgpack.StackError) as exc:
        kind = "JSON" if isinstance(data, str) else "msgpack"
        raise ProtocolError(None, f"message is not valid {kind}: {exc}") from None


def _depth(obj: Any, cap: int) -> int:
    """Nesting depth of decoded containers, counted up to ``cap`` (no deeper recursion)."""
    if cap <= 0 or not isinstance(obj, dict | list | tuple):
        return 0
    items = obj.values() if isinstance(obj, dict) else obj
    return 1 + max((_depth(v, cap - 1) for v in items), default=0)


def pack(message: dict) -> bytes:
    """Encode a server message (frame, error, subscribed, end) as msgpack."""
    return msgpack.packb(message, use_bin_type=True)


def unpack(data: bytes) -> dict:
    """Decode a server message."""
    return msgpack.unpackb(data, raw=False)


# --- scene --------------------------------------------------------------------------------------

class TauSource(StrEnum):
    """Where tau(t) comes from (the ``source`` of each entry of GET /scene's ``tau_sources``)."""

    CHECKPOINT = "checkpoint"
    """The checkpoint's own anchors (``anchors_us`` of GET /scene): the windows it was trained on."""
    STREAM = "stream"
    """The event stream's frames (a replay's or a camera's APS / RGB frames)."""
    ONLINE = "online"
    """Past the checkpoint's span: the stream's frames as online anchors (predicted by the event
    transition, then corrected against the frame; see ``ANCHOR_KINDS``), the checkpoint's last anchor
    until the first of them."""


ANCHOR_KINDS = ("checkpoint", "predicted", "corrected", "frame")
"""What the anchor of a render is (``HEADER_ANCHOR`` / a frame map's ``anchor``): one of the
checkpoint's, an online anchor's prediction (not corrected yet), an online anchor fitted to its frame, or
(a service learning from a cold start, before its first model) the stream's frame, moved by the events
since it."""


TRANSITIONS = ("select", "distilled", "g_phi", "none")
"""What moves online anchors past the span (GET /scene's ``online.transition``): chosen among the others
by how well each predicted the recent frames ("select"), the checkpoint's transition distilled from its
own motion, g_phi as trained, or nothing."""


TAU_SOURCE_KEYS = ("source", "t_min", "t_max", "t_us_min", "t_us_max")
"""Keys of one entry of GET /scene's ``tau_sources``."""


# --- errors -------------------------------------------------------------------------------------

class ErrorCode(StrEnum):
    """The ``error`` field of an error map: what went wrong, named for the client, never a class name.

    Each code has one HTTP status (``STATUS``); a websocket ``error`` message carries the same codes.
    """

    INVALID_INPUT = "invalid_input"
    """422: a malformed parameter or message; ``param`` names it."""
    TIME_UNAVAILABLE = "time_unavailable"
    """416: the time cannot be rendered now; ``valid_range`` says what can."""
    UNAUTHORIZED = "unauthorized"
    """401: the bearer token is missing or wrong."""
    BUSY = "busy"
    """503 with ``Retry-After``: every render slot is taken."""
    NOT_READY = "not_ready"
    """503: the model or the event source is not up (yet, or any more)."""
    RENDER_FAILED = "render_failed"
    """500: the render failed; the service lives on."""


STATUS = {ErrorCode.INVALID_INPUT: 422, ErrorCode.TIME_UNAVAILABLE: 416, ErrorCode.UNAUTHORIZED: 401,
          ErrorCode.BUSY: 503, ErrorCode.NOT_READY: 503, ErrorCode.RENDER_FAILED: 500}
"""The HTTP status of each error code."""


class ValidRange(TypedDict):
    """An interval of scene time that can be rendered now (inclusive bounds), in both units."""

    t_min: float
    """Seconds from the scene's start."""
    t_max: float
    """Seconds from the scene's start."""
    t_us_min: int
    """Absolute µs on the checkpoint's clock."""
    t_us_max: int
    """Absolute µs on the checkpoint's clock."""


@dataclass(frozen=True)
class ErrorBody:
    """The error map of HTTP bodies and websocket ``error`` messages (``ERROR_KEYS``; its ``type`` is
    ``"error"``)."""

    error: ErrorCode
    """What went wrong (each code has one HTTP status)."""
    detail: str
    """A message for a person."""
    param: str | None = None
    """The offending parameter or field (invalid_input), else null."""
    valid_range: ValidRange | None = None
    """What can be rendered now (time_unavailable), else null."""

    def to_message(self) -> dict:
        return {"type": "error", "error": self.error.value, "detail": self.detail, "param": self.param,
                "valid_range": self.valid_range}

    @classmethod
    def from_message(cls, message: dict, status: int | None = None) -> ErrorBody:
        """Read an error map; an unknown or missing code is taken from the HTTP status, else RENDER_FAILED."""
        try:
            code = ErrorCode(message.get("error"))
        except ValueError:
            by_status = {s: c for c, s in reversed(STATUS.items())}
            code = by_status.get(status, ErrorCode.RENDER_FAILED)
        return cls(code, str(message.get("detail")), message.get("param"), message.get("valid_range"))


def error_body(error: ErrorCode, detail: str, param: str | None = None,
               valid_range: dict | None = None) -> dict:
    """The error map of HTTP bodies and websocket ``error`` messages."""
    return ErrorBody(ErrorCode(error), detail, param, valid_range).to_message()


# --- event maps (GET /events) ------------------------------------------------------------------

EVENT_FORMATS = ("png", "msgpack")
EVENT_ON_RGB = (20, 90, 255)
"""Colour of a pixel whose window sums to a positive polarity (more ON than OFF events): blue."""
EVENT_OFF_RGB = (235, 40, 40)
"""Colour of a pixel whose window sums to a negative polarity: red."""
EVENT_MAP_DTYPE = "<i4"
"""The msgpack event map's ``data``: little-endian int32, the signed polarity sum per pixel."""
EVENT_HEADERS = (HEADER_T_US, HEADER_T, HEADER_ANCHOR_US, HEADER_EVENTS, HEADER_WIDTH, HEADER_HEIGHT)
EVENT_MAP_KEYS = (
    "type",  # "event_map"
    "t_us",  # absolute µs: the window's end (exclusive), the time a render at it shows
    "t",  # seconds from the scene's start
    "anchor_us",  # tau(t): the window's start (inclusive)
    "events",  # events in the window
    "width",  # the event sensor's width, px
    "height",
    "dtype",  # EVENT_MAP_DTYPE
    "data",  # bytes: the signed polarity sum per pixel, [height, width] row-major
)


@dataclass(frozen=True)
class EventMapMeta:
    """What the server says about one event map: the ``EVENT_HEADERS`` of GET /events, the keys of its
    msgpack map."""

    t_us: int
    t: float
    anchor_us: int
    events: int
    width: int
    height: int

    def headers(self) -> dict[str, str]:
        return {HEADER_T_US: str(self.t_us), HEADER_T: repr(self.t), HEADER_ANCHOR_US: str(self.anchor_us),
                HEADER_EVENTS: str(self.events), HEADER_WIDTH: str(self.width),
                HEADER_HEIGHT: str(self.height)}

    @classmethod
    def from_headers(cls, headers) -> EventMapMeta:
        return cls(int(headers[HEADER_T_US]), float(headers[HEADER_T]), int(headers[HEADER_ANCHOR_US]),
                   int(headers[HEADER_EVENTS]), int(headers[HEADER_WIDTH]), int(headers[HEADER_HEIGHT]))

    def to_message(self, data: bytes) -> dict:
        """The msgpack event map (``EVENT_MAP_KEYS``); ``data`` is the ``EVENT_MAP_DTYPE`` array's bytes."""
        if len(data) != 4 * self.width * self.height:
            raise ValueError(f"an event map of {self.width}x{self.height} is {4 * self.width * self.height} "
                             f"bytes, got {len(data)}")
        return {"type": "event_map", **asdict(self), "dtype": EVENT_MAP_DTYPE, "data": data}

    @classmethod
    def from_message(cls, message: dict) -> EventMapMeta:
        """Read an event-map map (its ``data`` is left to the caller)."""
        if message.get("type") != "event_map" or message.get("dtype") != EVENT_MAP_DTYPE:
            raise ProtocolError("type", f"not an event map of {EVENT_MAP_DTYPE}: "
                                        f"type={message.get('type')!r} dtype={message.get('dtype')!r}")
        return cls(int(message["t_us"]), float(message["t"]), int(message["anchor_us"]),
                   int(message["events"]), int(message["width"]), int(message["height"]))


# --- frames -------------------------------------------------------------------------------------

@dataclass(frozen=True)
class FrameMeta:
    """What the server says about one render: the ``HEADERS`` of GET /render, the keys of a frame map."""

    t_us: int
    """Absolute µs rendered."""
    t: float
    """The same, seconds from the scene's start."""
    anchor_us: int
    """tau(t): the anchor whose events window drove the deformation."""
    events: int
    """Events in the half-open window [tau(t), t)."""
    render_ms: float
    """Server time of the render and its encoding."""
    width: int
    """Image width, px."""
    height: int
    """Image height, px."""
    channels: int
    """1 (grey) or 3 (RGB)."""
    format: str
    """The format asked for: png | jpeg | msgpack (HTTP), jpeg | png | raw (websocket)."""
    anchor: str
    """What the anchor is (``ANCHOR_KINDS``): the checkpoint's, or an online anchor predicted or corrected."""
    projected: bool
    """The event camera's own view from an online anchor, clipped into the bounds its frame and the events
    since it put on each pixel (one contrast threshold either side of the frame moved by the events); the
    model renders what they leave open. False: the model's render alone."""
    render_mode: str = field(default="rgb", kw_only=True)
    """What the pixels show (``RENDER_MODES``): rgb, depth (grey, ``DEPTH_GREY_NEAR``) or alpha (grey)."""
    depth_near: float | None = field(default=None, kw_only=True)
    """Depth: the camera z (m) grey 255 stands for (the 1st percentile of the depths shown); else
    ``None``."""
    depth_far: float | None = field(default=None, kw_only=True)
    """Depth: the camera z (m) grey 1 stands for (the 99th percentile); else ``None``."""
    model_version: int | None = field(default=0, kw_only=True)
    """The model that rendered: 0 the checkpoint the service was given; 1, 2 ... the models a cold start
    learnt, in the order they went live; ``None`` none yet (the stream's frame moved by the events)."""

    def headers(self) -> dict[str, str]:
        """The ``HEADERS`` of a GET /render response, and a depth render's near and far."""
        out = {HEADER_T_US: str(self.t_us), HEADER_T: repr(self.t), HEADER_ANCHOR_US: str(self.anchor_us),
               HEADER_EVENTS: str(self.events), HEADER_RENDER_MS: f"{self.render_ms:.3f}",
               HEADER_WIDTH: str(self.width), HEADER_HEIGHT: str(self.height),
               HEADER_CHANNELS: str(self.channels), HEADER_ANCHOR: self.anchor,
               HEADER_PROJECTED: "true" if self.projected else "false", HEADER_MODE: self.render_mode,
               HEADER_MODEL: "none" if self.model_version is None else str(self.model_version)}
        if self.depth_near is not None and self.depth_far is not None:
            out |= {HEADER_DEPTH_NEAR: repr(self.depth_near), HEADER_DEPTH_FAR: repr(self.depth_far)}
        return out

    @classmethod
    def from_headers(cls, headers, format: str) -> FrameMeta:
        """Read the ``HEADERS`` of a GET /render response (any case-insensitive mapping)."""
        near, far = headers.get(HEADER_DEPTH_NEAR), headers.get(HEADER_DEPTH_FAR)
        version = headers.get(HEADER_MODEL, "0")
        return cls(int(headers[HEADER_T_US]), float(headers[HEADER_T]), int(headers[HEADER_ANCHOR_US]),
                   int(headers[HEADER_EVENTS]), float(headers[HEADER_RENDER_MS]), int(headers[HEADER_WIDTH]),
                   int(headers[HEADER_HEIGHT]), int(headers[HEADER_CHANNELS]), format,
                   headers.get(HEADER_ANCHOR, "checkpoint"), headers.get(HEADER_PROJECTED, "false") == "true",
                   render_mode=headers.get(HEADER_MODE, "rgb"),
                   depth_near=None if near is None else float(near),
                   depth_far=None if far is None else float(far),
                   model_version=None if version == "none" else int(version))

    def to_message(self, data: bytes, **stream: Any) -> dict:
        """A frame map (``FRAME_KEYS``): these fields and the image ``data``, plus the websocket's
        ``STREAM_KEYS`` when given in ``stream``."""
        unknown = set(stream) - set(STREAM_KEYS)
        if unknown:
            raise ValueError(f"not a frame key: {sorted(unknown)}")
        return {"type": "frame", **asdict(self), "data": data, **stream}

    @classmethod
    def from_message(cls, message: dict, format: str | None = None) -> FrameMeta:
        """Read a frame map (the ``data`` and stream keys are left to the caller)."""
        near, far = message.get("depth_near"), message.get("depth_far")
        return cls(int(message["t_us"]), float(message["t"]), int(message["anchor_us"]),
                   int(message["events"]), float(message["render_ms"]), int(message["width"]),
                   int(message["height"]), int(message["channels"]), format or message["format"],
                   message.get("anchor", "checkpoint"), bool(message.get("projected", False)),
                   render_mode=message.get("render_mode", "rgb"),
                   depth_near=None if near is None else float(near),
                   depth_far=None if far is None else float(far),
                   model_version=message.get("model_version", 0))


# The OpenAPI and AsyncAPI documents are generated from these types (server/wire_schema.py, by pydantic):
# let the generator read each field's docstring as its description.
for _documented in (Subscription, ValidRange, ErrorBody, FrameMeta):
    _documented.__pydantic_config__ = {"use_attribute_docstrings": True}
