"""The one place where errors become the wire's error codes, hence HTTP statuses (``protocol.STATUS``).

    InvalidInputError, PoseError, ProtocolError, request validation -> invalid_input (422), ``param``
    WindowUnavailable (t before the first anchor, outside the span,
      events not retained or not arrived yet)                      -> time_unavailable (416), ``valid_range``
    Busy (render queue full)                                       -> busy (503 + Retry-After)
    NotReady (model or source not up), DeviceDisconnected          -> not_ready (503)
    Unauthorized                                                   -> unauthorized (401 + WWW-Authenticate)
    RenderError, any other EdmcgsError, any unexpected exception   -> render_failed (500) with a message;
                                                                      the process lives on
"""

from __future__ import annotations

import logging

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse

from edmcgs.errors import (
    DeviceDisconnected,
    EdmcgsError,
    InvalidInputError,
    PoseError,
    RenderError,
    WindowUnavailable,
)
from edmcgs.protocol import STATUS, ErrorBody, ErrorCode, ProtocolError

log = logging.getLogger("edmcgs.server")


class Busy(EdmcgsError):
    """Every render worker and queue slot is taken; retry after ``retry_after_s``."""

    def __init__(self, retry_after_s: int = 1):
        super().__init__(f"the render queue is full; retry after {retry_after_s} s")
        self.retry_after_s = retry_after_s


class NotReady(EdmcgsError):
    """The model or the event source is not up (yet, or any more)."""


class Unauthorized(EdmcgsError):
    """The bearer token is missing or wrong."""


def code_of(exc: BaseException) -> ErrorCode:
    """The wire's error code of an exception (see the table above)."""
    if isinstance(exc, (InvalidInputError, ProtocolError, RequestValidationError)):
        return ErrorCode.INVALID_INPUT
    if isinstance(exc, WindowUnavailable):
        return ErrorCode.TIME_UNAVAILABLE
    if isinstance(exc, Busy):
        return ErrorCode.BUSY
    if isinstance(exc, (NotReady, DeviceDisconnected)):
        return ErrorCode.NOT_READY
    if isinstance(exc, Unauthorized):
        return ErrorCode.UNAUTHORIZED
    return ErrorCode.RENDER_FAILED


def status_of(exc: BaseException) -> int:
    """HTTP status code of an exception: the status of its error code."""
    return STATUS[code_of(exc)]


def body_of(exc: BaseException) -> dict:
    """The protocol's error map for an exception (``ErrorBody``)."""
    if isinstance(exc, RequestValidationError):
        first = exc.errors()[0] if exc.errors() else {}
        loc = [str(p) for p in first.get("loc", ()) if p not in ("query", "body", "header", "path")]
        param = loc[0] if loc else None
        detail = f"{param}: {first.get('msg', 'invalid value')}" if param else str(first.get("msg", exc))
        if "input" in first:
            detail += f" (got {first['input']!r})"
        return ErrorBody(ErrorCode.INVALID_INPUT, detail, param).to_message()
    code = code_of(exc)
    if code is ErrorCode.RENDER_FAILED and not isinstance(exc, RenderError | EdmcgsError):
        detail = f"render failed: {type(exc).__name__}: {exc}"
    else:
        detail = str(exc) or type(exc).__name__
    param = getattr(exc, "param", None) or ("pose" if isinstance(exc, PoseError) else None)
    return ErrorBody(code, detail, param, getattr(exc, "valid_range", None)).to_message()


def response_of(exc: BaseException) -> JSONResponse:
    """The JSON error response for an exception."""
    status = status_of(exc)
    headers = {}
    if isinstance(exc, Busy):
        headers["Retry-After"] = str(exc.retry_after_s)
    elif isinstance(exc, NotReady | DeviceDisconnected):
        headers["Retry-After"] = "1"
    elif isinstance(exc, Unauthorized):
        headers["WWW-Authenticate"] = 'Bearer realm="edmcgs"'
    if status == 500:
        log.error("request failed: %s", exc, exc_info=exc)
    return JSONResponse(body_of(exc), status_code=status, headers=headers)


def install(app: FastAPI) -> None:
    """Register the handlers on ``app`` so every route answers errors the same way."""

    async def handle(_request: Request, exc: Exception) -> JSONResponse:
        return response_of(exc)

    app.add_exception_handler(RequestValidationError, handle)
    app.add_exception_handler(EdmcgsError, handle)
    app.add_exception_handler(ProtocolError, handle)
    app.add_exception_handler(Exception, handle)
