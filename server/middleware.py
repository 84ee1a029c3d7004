"""ASGI middleware around every route: the bearer-token check and the per-route request metrics."""

from __future__ import annotations

import time
from urllib.parse import parse_qs

from edmcgs.server.auth import check_token
from edmcgs.server.errors import Unauthorized, response_of


class AccessMiddleware:
    """With ``token`` set, refuse any request without ``Authorization: Bearer <token>`` or ``?token=``
    (the browser viewer's page load and websocket cannot set headers): HTTP 401, websocket closed
    with code 1008 before the handshake completes (HTTP 403). Then count and time HTTP requests.
    """

    def __init__(self, app, token: str | None):
        self.app = app
        self.token = token

    async def __call__(self, scope, receive, send):
        kind = scope["type"]
        if kind not in ("http", "websocket"):
            await self.app(scope, receive, send)
            return
        if self.token is not None:
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


def _record(scope, status: int, seconds: float) -> None:
    service = getattr(scope["app"].state, "service", None) if "app" in scope else None
    if service is None:
        return
    route = scope.get("route")
    # Label by route template, never by raw path: a scanner must not create unbounded series.
    name = "unmatched" if route is None else getattr(route, "path", "") or "/"
    service.metrics.requests.inc(1, name, str(status))
    service.metrics.latency.observe(seconds, name)


def _header(scope, name: bytes) -> str | None:
    for key, value in scope.get("headers", ()):
        if key.lower() == name:
            return value.decode("latin-1")
    return None


def _query_token(scope) -> str | None:
    values = parse_qs(scope.get("query_string", b"").decode("latin-1")).get("token")
    return values[0] if values else None
