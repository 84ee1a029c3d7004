"""ASGI middleware around every route: the bearer-token check and the per-route request metrics."""

from __future__ import annotations

import ipaddress
import re
import time
from urllib.parse import parse_qs

from fastapi.responses import JSONResponse

from edmcgs.protocol import ErrorBody, ErrorCode
from edmcgs.server.auth import check_token
from edmcgs.server.errors import Busy, Unauthorized, body_of, response_of
from edmcgs.server.routes.stream import CLOSE_TRY_AGAIN_LATER


class AccessMiddleware:
    """At most ``max_in_flight`` requests and websockets in progress (None: no bound): one more is
    answered 503 busy with Retry-After, or closed with 1013. Connections that have not sent a request
    never count (``connections.py`` closes them). Then: a foreign Host or Origin is refused (421,
    websocket 1008), and with ``token`` set, any request without ``Authorization: Bearer <token>`` or
    ``?token=`` (the browser viewer's page load and websocket cannot set headers): HTTP 401, websocket
    closed with code 1008 before the handshake completes (HTTP 403). Then count and time HTTP requests.
    """

    def __init__(self, app, token: str | None, *, allowed_hosts: list[str] | None = None,
                 open_paths: frozenset[str] = frozenset(), max_in_flight: int | None = None):
        self.app = app
        self.token = token
        self.allowed_hosts = allowed_hosts
        self.open_paths = open_paths
        self.max_in_flight = max_in_flight
        self.in_flight = 0

    async def __call__(self, scope, receive, send):
        kind = scope["type"]
        if kind not in ("http", "websocket"):
            await self.app(scope, receive, send)
            return
        if self.max_in_flight is not None and self.in_flight >= self.max_in_flight:
            await self._busy(scope, receive, send)
            return
        self.in_flight += 1
        try:
            await self._checked(scope, receive, send)
        finally:
            self.in_flight -= 1

    async def _busy(self, scope, receive, send) -> None:
        busy = Busy(retry_after_s=1)
        detail = (f"the server already handles {self.max_in_flight} requests and streams "
                  "(EDMCGS_MAX_CONNECTIONS); retry later")
        if scope["type"] == "websocket":
            await send({"type": "websocket.close", "code": CLOSE_TRY_AGAIN_LATER, "reason": detail[:120]})
            return
        await JSONResponse(body_of(busy) | {"detail": detail}, status_code=503,
                           headers={"Retry-After": str(busy.retry_after_s)})(scope, receive, send)
        _record(scope, 503, 0.0)

    async def _checked(self, scope, receive, send):
        kind = scope["type"]
        refused = foreign(scope, self.allowed_hosts)
        if refused is not None:
            if kind == "websocket":
                await send({"type": "websocket.close", "code": 1008, "reason": refused[:120]})
            else:
                await misdirected(refused)(scope, receive, send)
                _record(scope, 421, 0.0)
            return
        if self.token is not None and _route_path(scope) not in self.open_paths:
            try:
                check_token(self.token, _header(scope, b"authorization"), _query_token(scope))
            except Unauthorized as exc:
                if kind == "websocket":
                    await send({"type": "websocket.close", "code": 1008, "reason": str(exc)[:120]})
                else:
                    await response_of(exc)(scope, receive, send)
                    _record(scope, 401, 0.0)
                return
        if kind == "websocket":
            await self.app(scope, receive, send)
            return
        status = 500
        t0 = time.perf_counter()

        async def send_wrapper(message):
            nonlocal status
            if message["type"] == "http.response.start":
                status = message["status"]
            await send(message)

        try:
            await self.app(scope, receive, send_wrapper)
        finally:
            _record(scope, status, time.perf_counter() - t0)


def foreign(scope, allowed_hosts: list[str] | None) -> str | None:
    """Why a request comes from a foreign site (DNS rebinding: a Host not ours; a web page's websocket:
    an Origin not ours), or None; ``allowed_hosts`` None or with ``*``: any. The one check of every
    page, the single process's and the Ray gateway's own. A Host or Origin that is not plainly a host
    and a port (``127.0.0.1:1@evil.com``, ``http://localhost:1@evil.com``) is foreign."""
    if allowed_hosts is None or "*" in allowed_hosts:
        return None
    allowed = {h.lower() for h in allowed_hosts}
    raw = _header(scope, b"host")
    host = _hostname(raw)
    if host is None or host not in allowed:
        return (f"Host {(raw or '')[:60]!r} is not one this server answers to (EDMCGS_ALLOWED_HOSTS); "
                "a DNS-rebinding page is refused")
    origin = _header(scope, b"origin")
    if origin is not None:
        match = _ORIGIN.fullmatch(origin.strip())
        origin_host = _hostname(match["netloc"]) if match else None
        if origin_host is None or origin_host not in allowed:
            return f"Origin {origin[:60]!r} is not allowed (EDMCGS_ALLOWED_HOSTS)"
    return None


def misdirected(reason: str) -> JSONResponse:
    """The answer to a foreign request: 421, the error body naming the Host or Origin."""
    return JSONResponse(ErrorBody(ErrorCode.INVALID_INPUT, reason, "host").to_message(), status_code=421)


_NETLOC = re.compile(r"(?:\[(?P<v6>[0-9a-f:.]+)\]|(?P<name>[a-z0-9_.-]+))(?::[0-9]{1,5})?")
"""A Host header (or an origin's netloc): a name or a bracketed IPv6 address, then a port; nothing else."""
_ORIGIN = re.compile(r"[a-z][a-z0-9+.-]*://(?P<netloc>[^/?#\s]*)", re.IGNORECASE)
"""An Origin header: a scheme and a netloc, no path (browsers send no more)."""


def _hostname(netloc: str | None) -> str | None:
    """The host name of a Host header or an origin's netloc, lowercase, without port or brackets; None
    for anything else (user info, a path, stray characters)."""
    if not netloc:
        return None
    netloc = netloc.strip().lower()
    match = _NETLOC.fullmatch(netloc)
    if match is not None:
        v6 = match["v6"]
        return match["name"] if v6 is None else (v6 if _is_ipv6(v6) else None)
    return netloc if _is_ipv6(netloc) else None  # an unbracketed IPv6 address, as some clients send


def _is_ipv6(text: str) -> bool:
    try:
        ipaddress.IPv6Address(text)
    except ValueError:
        return False
    return True


def _record(scope, status: int, seconds: float) -> None:
    service = getattr(scope["app"].state, "service", None) if "app" in scope else None
    if service is None:
        return
    route = scope.get("route")
    # Label by route template, never by raw path: a scanner must not create unbounded series.
    name = "unmatched" if route is None else getattr(route, "path", "") or "/"
    service.metrics.requests.labels(name, str(status)).inc()
    service.metrics.latency.labels(name).observe(seconds)


def _route_path(scope) -> str:
    """The path within the app: ASGI's ``path`` includes ``root_path`` (the prefix a proxy serves it
    under, as the Ray gateway does)."""
    path, root = scope.get("path", ""), scope.get("root_path", "")
    if root and path.startswith(root + "/"):
        return path[len(root):]
    return path


def _header(scope, name: bytes) -> str | None:
    for key, value in scope.get("headers", ()):
        if key.lower() == name:
            return value.decode("latin-1")
    return None


def _query_token(scope) -> str | None:
    values = parse_qs(scope.get("query_string", b"").decode("latin-1")).get("token")
    return values[0] if values else None
