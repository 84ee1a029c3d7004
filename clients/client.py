"""Python client of the edmcgs service: ``Client(base_url, token).render(...)``, ``.stream(...)``.

Imports nothing of the project but the wire schema (``edmcgs.protocol``)::

    with Client("http://127.0.0.1:8000") as c:
        scene = c.scene()
        image, meta = c.render(t=0.5)                          # uint8 [H, W, C] and RenderMeta
        png, meta = c.render(t=0.5, pose=[...16...], format="png")
        depth, meta = c.render(t=0.5, mode="depth")            # grey [H, W, 1], meta.depth_near / _far
        z = depth_metres(depth, meta)                          # camera z in m [H, W]; NaN: no surface
        emap, meta = c.events(t=0.5)                           # I_E of its window: int32 [H, W], EventMapMeta
        with c.stream({"mode": "sweep", "t0": 0, "t1": 1, "fps": 30}) as frames:
            for frame in frames:                               # Frame, newest first when slow
                ...
                frames.update(pose=[...])                      # change the subscription mid-stream

Errors are typed by HTTP status (``InvalidRequest`` 422, ``TimeUnavailable`` 416, ``Unauthorized``
401, ``Busy`` 503 with ``retry_after_s``, ``ServerError`` 500) and carry the server's message.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from types import TracebackType
from urllib.parse import urlsplit, urlunsplit

import httpx
import numpy as np
from websockets.exceptions import ConnectionClosed, InvalidStatus
from websockets.sync.client import ClientConnection, connect

from edmcgs import protocol

# --- errors -------------------------------------------------------------------------------------


class ServiceError(Exception):
    """The service answered with an error; ``status`` is the HTTP code (0 for a websocket message)."""

    def __init__(self, status: int, detail: str, *, error: str | None = None, param: str | None = None,
                 valid_range: dict | None = None):
        super().__init__(f"{status} {error or 'error'}: {detail}" if status else f"{error}: {detail}")
        self.status, self.detail, self.error, self.param, self.valid_range = (
            status, detail, error, param, valid_range)


class InvalidRequest(ServiceError):
    """422: a parameter is malformed; ``param`` names it."""


class TimeUnavailable(ServiceError):
    """416: the time asked for cannot be rendered now; ``valid_range`` says what can."""


class Unauthorized(ServiceError):
    """401: the token is missing or wrong."""


class Busy(ServiceError):
    """503: the server is busy or not ready; retry after ``retry_after_s`` seconds."""

    retry_after_s: float = 1.0


class ServerError(ServiceError):
    """500 (or any other status): the render failed on the server."""


_Code = protocol.ErrorCode
_BY_CODE = {_Code.INVALID_INPUT: InvalidRequest, _Code.TIME_UNAVAILABLE: TimeUnavailable,
            _Code.UNAUTHORIZED: Unauthorized, _Code.BUSY: Busy, _Code.NOT_READY: Busy,
            _Code.RENDER_FAILED: ServerError}


def _raise_for(response: httpx.Response) -> None:
    if response.is_success:
        return
    try:
        body = response.json()
    except ValueError:
        body = {"detail": response.text or response.reason_phrase}
    if not isinstance(body, dict):
        body = {"detail": str(body)}
    err = protocol.ErrorBody.from_message(body, response.status_code)
    exc = _BY_CODE[err.error](response.status_code, err.detail, error=err.error, param=err.param,
                              valid_range=err.valid_range)
    if isinstance(exc, Busy):
        try:
            exc.retry_after_s = float(response.headers.get("Retry-After", 1))
        except ValueError:
            exc.retry_after_s = 1.0
    raise exc


def _error_message(message: dict) -> ServiceError:
    err = protocol.ErrorBody.from_message(message)
    return _BY_CODE[err.error](0, err.detail, error=err.error, param=err.param, valid_range=err.valid_range)


# --- results ------------------------------------------------------------------------------------


RenderMeta = protocol.FrameMeta
"""What the server says about a render (from headers, or the msgpack body); ``format`` is the one asked
for: "png", "jpeg" or "msgpack"."""


@dataclass(frozen=True)
class Frame(protocol.FrameMeta):
    """One websocket frame: the render's ``FrameMeta`` plus the stream's numbering and the encoded image.
    ``image()`` decodes it to uint8 [H, W, C]."""

    seq: int
    dropped: int
    data: bytes
    arrived_unix_us: int | None = None
    head_arrived_unix_us: int | None = None

    def image(self) -> np.ndarray:
        """The pixels, uint8 [height, width, channels] (PNG / JPEG decoded with Pillow)."""
        return decode_image(self.data, self.format, self.width, self.height, self.channels)


def decode_image(data: bytes, fmt: str, width: int, height: int, channels: int) -> np.ndarray:
    """uint8 [H, W, C] from wire bytes ("raw" pixels, "png" or "jpeg")."""
    if fmt == "raw":
        return np.frombuffer(data, dtype=np.uint8).reshape(height, width, channels)
    import io

    from PIL import Image

    arr = np.asarray(Image.open(io.BytesIO(data)))
    return arr[..., None] if arr.ndim == 2 else arr


def depth_metres(grey: np.ndarray, meta: protocol.FrameMeta) -> np.ndarray:
    """A depth render's grey pixels [H, W] or [H, W, 1] -> camera z in m, float64 [H, W]: linear from
    ``meta.depth_near`` (grey 255) to ``meta.depth_far`` (grey 1), NaN where the splats' opacity is below
    ``protocol.DEPTH_MIN_ALPHA`` (grey 0); the server's mapping (``protocol.DEPTH_GREY_NEAR``) undone, to
    within a grey step."""
    if meta.render_mode != "depth":
        raise ValueError(f"not a depth render (render_mode {meta.render_mode!r})")
    grey = np.asarray(grey)
    grey = grey[..., 0] if grey.ndim == 3 else grey
    if meta.depth_near is None or meta.depth_far is None:
        return np.full(grey.shape, np.nan)
    lo, hi = protocol.DEPTH_GREY_FAR, protocol.DEPTH_GREY_NEAR
    near, far = meta.depth_near, meta.depth_far
    z = far - (grey.astype(np.float64) - lo) / (hi - lo) * (far - near)
    return np.where(grey != protocol.DEPTH_GREY_NONE, z, np.nan)


def _frame(message: dict) -> Frame:
    return Frame(**{k: message.get(k) for k in Frame.__dataclass_fields__})


# --- the client ---------------------------------------------------------------------------------


class Client:
    """A connection to one edmcgs service. Thread-safe for ``render`` (httpx's pool); a context manager."""

    def __init__(self, base_url: str = "http://127.0.0.1:8000", token: str | None = None, *,
                 timeout: float = 30.0):
        self.base_url = base_url.rstrip("/")
        self.token = token
        self.timeout = timeout
        headers = {"Authorization": f"Bearer {token}"} if token else {}
        self._http = httpx.Client(base_url=self.base_url, headers=headers, timeout=timeout)

    # HTTP
    def scene(self) -> dict:
        """GET /scene: span, anchors, intrinsics, trajectory, what can be rendered now, the live head."""
        return self._get("/scene").json()

    def health(self) -> dict:
        """GET /healthz (raises Busy while the server is not ready)."""
        return self._get("/healthz").json()

    def metrics(self) -> str:
        """GET /metrics: Prometheus text."""
        return self._get("/metrics").text

    def render(self, t: float | None = None, *, t_us: int | None = None, pose=None,
               width: int | None = None, height: int | None = None,
               format: str = "msgpack", mode: str = "rgb") -> tuple[np.ndarray | bytes, RenderMeta]:
        """GET /render. ``t`` seconds from the scene's start, or ``t_us`` absolute (neither: the live head).

        pose: camera-to-world, 16 numbers (row-major), 7 (tx,ty,tz,qw,qx,qy,qz: the quaternion's w
        first, where TUM files put it last), a 4x4 array, or None (the event camera's own pose).
        format "msgpack" returns uint8 pixels [H, W, C]; "png" / "jpeg" the bytes.
        mode (``protocol.RENDER_MODES``): "rgb"; "depth", the expected camera z as grey [H, W, 1] with
        the meta's ``depth_near`` / ``depth_far`` (``depth_metres`` reads it back; take png or msgpack:
        jpeg blurs the grey); "alpha", the splats' accumulated opacity as grey.
        """
        if format not in protocol.RENDER_FORMATS:
            raise ValueError(f"format must be one of {protocol.RENDER_FORMATS}, got {format!r}")
        if mode not in protocol.RENDER_MODES:
            raise ValueError(f"mode must be one of {protocol.RENDER_MODES}, got {mode!r}")
        params: dict = {"format": format, "mode": mode}
        if t is not None:
            params["t"] = repr(float(t))
        if t_us is not None:
            params["t_us"] = str(int(t_us))
        if pose is not None:
            params["pose"] = ",".join(repr(v) for v in _pose_numbers(pose))
        if width is not None:
            params["width"] = str(int(width))
        if height is not None:
            params["height"] = str(int(height))
        response = self._get("/render", params=params)
        if format == "msgpack":
            body = protocol.unpack(response.content)
            image = decode_image(body["data"], body["format"], body["width"], body["height"],
                                 body["channels"])
            return image, protocol.FrameMeta.from_message(body, format)
        return response.content, protocol.FrameMeta.from_headers(response.headers, format)

    def ply(self, t: float | None = None, *, t_us: int | None = None) -> bytes:
        """GET /ply: the Gaussians at ``t`` seconds from the scene's start, or ``t_us`` absolute (neither:
        the live head), as a 3DGS PLY file (what ``edmcgs export-ply`` writes)."""
        params = {}
        if t is not None:
            params["t"] = repr(float(t))
        if t_us is not None:
            params["t_us"] = str(int(t_us))
        return self._get("/ply", params=params).content

    def events(self, t: float | None = None, *, t_us: int | None = None,
               format: str = "msgpack") -> tuple[np.ndarray | bytes, protocol.EventMapMeta]:
        """GET /events: the event map I_E of the window a render at ``t`` / ``t_us`` uses (neither: the
        live head). format "msgpack" returns the signed polarity sum per pixel, int32 [H, W]; "png" the
        DV-style RGBA picture's bytes."""
        if format not in protocol.EVENT_FORMATS:
            raise ValueError(f"format must be one of {protocol.EVENT_FORMATS}, got {format!r}")
        params: dict = {"format": format}
        if t is not None:
            params["t"] = repr(float(t))
        if t_us is not None:
            params["t_us"] = str(int(t_us))
        response = self._get("/events", params=params)
        if format == "msgpack":
            body = protocol.unpack(response.content)
            meta = protocol.EventMapMeta.from_message(body)
            emap = np.frombuffer(body["data"], dtype=protocol.EVENT_MAP_DTYPE)
            return emap.reshape(meta.height, meta.width).astype(np.int32), meta
        return response.content, protocol.EventMapMeta.from_headers(response.headers)

    def _get(self, path: str, params: dict | None = None) -> httpx.Response:
        response = self._http.get(path, params=params)
        _raise_for(response)
        return response

    # websocket
    def stream(self, subscription: dict | protocol.Subscription | None = None, *,
               timeout: float | None = None) -> Stream:
        """Open WS /stream with ``subscription`` (a map of Subscription fields). See ``Stream``."""
        if isinstance(subscription, protocol.Subscription):
            message = subscription.to_message()
        else:
            message = dict(subscription or {})
        try:  # fail here, with the field named, rather than on the server
            protocol.Subscription().updated(message)
        except protocol.ProtocolError as exc:
            raise InvalidRequest(0, exc.detail, error=_Code.INVALID_INPUT, param=exc.param) from None
        parts = urlsplit(self.base_url)
        scheme = "wss" if parts.scheme == "https" else "ws"
        url = urlunsplit((scheme, parts.netloc, parts.path + "/stream", "", ""))
        headers = {"Authorization": f"Bearer {self.token}"} if self.token else None
        try:
            # Entered as a context manager (what websockets >= 17 asks for); Stream exits it on close.
            opened = connect(url, additional_headers=headers, open_timeout=self.timeout, close_timeout=2,
                             max_size=2**28)
            ws = opened.__enter__()
        except InvalidStatus as exc:
            status = exc.response.status_code
            code = protocol.ErrorBody.from_message({}, status).error
            cls = Unauthorized if status in (401, 403) else _BY_CODE[code]
            raise cls(status, f"websocket refused: {exc.response.body.decode(errors='replace') or status}") \
                from None
        return Stream(ws, opened, message, self.timeout if timeout is None else timeout)

    def close(self) -> None:
        self._http.close()

    def __enter__(self) -> Client:
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.close()


class Stream:
    """An open websocket stream: iterate for ``Frame``s; ``update(**fields)`` changes the subscription.

    Iteration ends when a sweep without loop is done or the server closes. An ``error`` message from
    the server raises its typed error (the stream stays usable: send a corrected ``update``).
    """

    def __init__(self, ws: ClientConnection, opened, message: dict, timeout: float):
        self._ws = ws
        self._opened = opened
        self._timeout = timeout
        self.subscription: dict | None = None  # as confirmed by the server
        self._send(message)

    def _send(self, message: dict) -> None:
        self._ws.send(protocol.pack(message))

    def update(self, **fields) -> None:
        """Send a partial subscription (e.g. ``pose=[...]``); fields not given keep their values."""
        if fields.get("pose") is not None:
            fields["pose"] = _pose_numbers(fields["pose"])
        self._send(fields)

    def receive(self, timeout: float | None = None) -> Frame | None:
        """The next frame (None when the stream ended). Raises TimeoutError after ``timeout`` s."""
        while True:
            try:
                data = self._ws.recv(timeout=self._timeout if timeout is None else timeout)
            except ConnectionClosed:
                return None
            if isinstance(data, str):
                data = data.encode()
            message = protocol.unpack(data)
            kind = message.get("type")
            if kind == "frame":
                return _frame(message)
            if kind == "subscribed":
                self.subscription = message.get("subscription")
            elif kind == "error":
                raise _error_message(message)
            elif kind == "end":
                return None

    def __iter__(self) -> Iterator[Frame]:
        while (frame := self.receive()) is not None:
            yield frame

    def close(self) -> None:
        self._opened.__exit__(None, None, None)

    def __enter__(self) -> Stream:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _pose_numbers(pose) -> list[float]:
    """16 or 7 finite floats from a sequence or array (a 4x4 too); InvalidRequest naming ``pose``."""
    try:
        flat = np.asarray(pose, dtype=np.float64).reshape(-1).tolist()
        return protocol.check_pose_numbers(flat)
    except (TypeError, ValueError) as exc:
        detail = exc.detail if isinstance(exc, protocol.ProtocolError) else f"pose must be numbers: {exc}"
        raise InvalidRequest(0, detail, error=_Code.INVALID_INPUT, param="pose") from None
