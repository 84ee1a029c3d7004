"""The Ray gateway's own pages (``/scenes``, ``/``, ``/healthz``, ``/docs``, ``/openapi.json``, an
unknown scene's 404 and websocket) apply the single process's Host and Origin check: called on the
gateway's handlers themselves, no Ray started."""

from __future__ import annotations

import asyncio

import pytest

pytest.importorskip("ray.serve", reason="the 'ray' extra is not installed")

from fastapi import FastAPI
from starlette.requests import Request
from starlette.websockets import WebSocket

from edmcgs.server.ray_serve.gateway import Gateway
from edmcgs.server.settings import host_allowlist

FOREIGN = [{"host": "evil.com"}, {"host": "127.0.0.1:1@evil.com"},
           {"host": "127.0.0.1:8000", "origin": "http://localhost:1@evil.com"},
           {"host": "127.0.0.1:8000", "origin": "https://evil.com"}]


def _gateway(token: str | None = None):
    # The class as written (Serve's ingress wraps it): its handlers, without the actors it starts.
    gateway = object.__new__(Gateway.__bases__[0])
    gateway.scenes, gateway.info, gateway.retriers = {}, {}, {}
    gateway.token, gateway.allowed_hosts = token, host_allowlist("127.0.0.1", None)
    return gateway


def _request(headers: dict, path: str = "/") -> Request:
    return Request({"type": "http", "method": "GET", "path": path, "query_string": b"", "app": FastAPI(),
                    "headers": [(k.encode(), v.encode()) for k, v in headers.items()]})


def _pages(gateway, request):
    return [gateway.list_scenes(request), gateway.index(request), gateway.healthz(request),
            gateway.openapi(request), gateway.docs(request),
            gateway.scene_route("nowhere", "render", request)]


@pytest.mark.parametrize("headers", FOREIGN)
def test_a_foreign_host_or_origin_gets_421_from_every_page(headers):
    async def main():
        for answer in await asyncio.gather(*_pages(_gateway(token="t"), _request(headers))):
            assert answer.status_code == 421 and b"host" in answer.body

    asyncio.run(main())


def test_the_gateways_own_names_are_served():
    async def main():
        request = _request({"host": "localhost:8000", "origin": "http://127.0.0.1:8000"})
        listed, index, health, schema, docs, unknown = await asyncio.gather(*_pages(_gateway(), request))
        assert listed == {"scenes": []} and health["ready"] is True
        assert index.status_code == schema.status_code == docs.status_code == 200
        assert unknown.status_code == 404

    asyncio.run(main())


def test_an_unknown_scenes_websocket_from_a_foreign_origin_is_closed_before_accept():
    sent = []

    async def receive():
        return {"type": "websocket.connect"}

    async def send(message):
        sent.append(message)

    scope = {"type": "websocket", "path": "/scenes/nowhere/stream", "query_string": b"",
             "headers": [(b"host", b"127.0.0.1:8000"), (b"origin", b"http://localhost:1@evil.com")]}
    asyncio.run(_gateway().stream(WebSocket(scope, receive, send), "nowhere"))
    assert [m["type"] for m in sent] == ["websocket.close"] and sent[0]["code"] == 1008
