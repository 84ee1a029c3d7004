"""The gateway: Serve's FastAPI ingress. ``/scenes`` lists the scenes; ``/scenes/{name}/...`` is that
scene's API, the very routes of ``edmcgs-serve`` (``/render``, ``/scene``, ``/healthz``, ``/metrics``,
``/stream``, the viewer at ``/scenes/{name}/``), answered by one of its replicas.

A call that fails because its replica died is sent again (``retry.py``): the client sees the answer of
a live replica, never the death. A websocket is relayed to a replica (``relay.py``).
"""


import asyncio
import html
import json
import logging

import ray
from fastapi import FastAPI, Request, WebSocket
from fastapi.openapi.docs import get_swagger_ui_html
from fastapi.responses import HTMLResponse, JSONResponse, RedirectResponse, Response
from ray import serve
from ray.serve.exceptions import BackPressureError

from edmcgs import protocol
from edmcgs.server.auth import check_token
from edmcgs.server.errors import Unauthorized
from edmcgs.server.middleware import foreign, misdirected
from edmcgs.server.ray_serve.mailbox import Mailbox
from edmcgs.server.ray_serve.relay import StreamRelay
from edmcgs.server.ray_serve.retry import Retrier, retryable
from edmcgs.server.ray_serve.scene import REPLICA_HEADER
from edmcgs.server.ray_serve.scrape import BOARD_NAME, MetricsBoard, gateway_series, merge

log = logging.getLogger("edmcgs.server.ray")

HEALTH_TIMEOUT_S = 5.0
"""How long ``/scenes`` waits for a scene's health before reporting it unknown."""

app = FastAPI(title="edmcgs on Ray Serve", version="0.1.0",
              description="Many scenes: GET /scenes lists them; each scene's API (the one of "
                          "edmcgs-serve) lives under /scenes/{name}/.",
              docs_url=None, redoc_url=None, openapi_url=None)  # served below, behind the Host check


def _error(status: int, code: protocol.ErrorCode, detail: str, retry_after: bool = False) -> JSONResponse:
    return JSONResponse(protocol.ErrorBody(code, detail).to_message(), status_code=status,
                        headers={"Retry-After": "1"} if retry_after else None)


def _client(request_or_ws) -> str:
    client = request_or_ws.client
    return client.host if client is not None else "127.0.0.1"


@serve.ingress(app)
class Gateway:
    """``scenes``: name -> the scene deployment's handle; ``info``: name -> what ``/scenes`` says of it."""

    def __init__(self, scenes: dict, info: dict[str, dict], token: str | None = None,
                 allowed_hosts: list[str] | None = None):
        self.scenes = scenes
        self.info = info
        # The gateway's own pages; each scene's routes check the scene's in the scene's app.
        self.token = token
        self.allowed_hosts = allowed_hosts
        self.retriers = {name: Retrier() for name in scenes}
        # Actors of this gateway's, gone with it: client messages into running replica sessions, and
        # the replicas' metrics (found by name: each replica pushes to it).
        self.mailbox = ray.remote(Mailbox).options(num_cpus=0, max_concurrency=10_000).remote()
        try:
            app_name = serve.get_replica_context().app_name
        except Exception:  # constructed outside Serve
            app_name = "local"
        self.board = ray.remote(MetricsBoard).options(
            num_cpus=0, name=BOARD_NAME.format(app=app_name), namespace="serve", get_if_exists=True).remote()

    def _misdirected(self, request: Request) -> JSONResponse | None:
        """421 for a foreign Host or Origin (the single process's check, ``middleware.foreign``)."""
        refused = foreign(request.scope, self.allowed_hosts)
        return None if refused is None else misdirected(refused)

    def _auth(self, request: Request) -> JSONResponse | None:
        """421 for a foreign Host or Origin, then 401 unless the request carries the token (when one is
        set): the checks of every route of a scene, for the pages the gateway answers itself."""
        refused = self._misdirected(request)
        if refused is not None:
            return refused
        try:
            check_token(self.token, request.headers.get("authorization"), request.query_params.get("token"))
        except Unauthorized as exc:
            return JSONResponse(protocol.ErrorBody(protocol.ErrorCode.UNAUTHORIZED, str(exc)).to_message(),
                                status_code=401, headers={"WWW-Authenticate": 'Bearer realm="edmcgs"'})
        return None

    # ------------------------------------------------------------------ index
    async def _health(self, name: str) -> dict:
        """The scene's /healthz as its replica sees it (asked with the scene's own token)."""
        try:
            handle = self.scenes[name]
            result = await asyncio.wait_for(self.retriers[name].run(lambda: handle.probe.remote("/healthz")),
                                            HEALTH_TIMEOUT_S)
            return json.loads(result.body)
        except Exception as exc:
            return {"ready": False, "source": "unknown", "source_error": f"{type(exc).__name__}: {exc}"}

    @app.get("/scenes", summary="The scenes served, each with its health")
    async def list_scenes(self, request: Request):
        refused = self._auth(request)
        if refused is not None:
            return refused
        names = list(self.scenes)
        healths = await asyncio.gather(*(self._health(n) for n in names))
        return {"scenes": [{**self.info[n], "url": f"/scenes/{n}/", "health": h}
                           for n, h in zip(names, healths, strict=True)]}

    @app.get("/healthz", summary="200 while the gateway serves; each scene's readiness in the body (open "
                                 "to probes, like a scene's with open_probes)")
    async def healthz(self, request: Request):
        refused = self._misdirected(request)
        if refused is not None:
            return refused
        names = list(self.scenes)
        healths = await asyncio.gather(*(self._health(n) for n in names))
        return {"ready": True, "retries": sum(r.retries for r in self.retriers.values()),
                "scenes": {n: bool(h.get("ready")) for n, h in zip(names, healths, strict=True)}}

    @app.get("/", response_class=HTMLResponse, include_in_schema=False)
    async def index(self, request: Request) -> Response:
        """Pick a scene: each link opens the browser viewer on that scene."""
        refused = self._auth(request)
        if refused is not None:
            return refused
        items = "".join(f'<li><a href="scenes/{html.escape(n)}/">{html.escape(n)}</a> — '
                        f'{html.escape(str(self.info[n].get("checkpoint")))}</li>' for n in self.scenes)
        return HTMLResponse(f"<!doctype html><meta charset=utf-8><title>edmcgs scenes</title>"
                            f"<h1>edmcgs scenes</h1><ul>{items}</ul>")

    @app.get("/openapi.json", include_in_schema=False)
    async def openapi(self, request: Request) -> Response:
        return self._misdirected(request) or JSONResponse(request.app.openapi())

    @app.get("/docs", include_in_schema=False)
    async def docs(self, request: Request) -> Response:
        return self._misdirected(request) or get_swagger_ui_html(
            openapi_url="/openapi.json", title="edmcgs on Ray Serve: Swagger UI")

    # ------------------------------------------------------------------ one scene
    async def _http(self, name: str, method: str, path: str, query: str, headers: list, client: str
                    = "127.0.0.1"):
        handle = self.scenes[name]
        root = f"/scenes/{name}"
        return await self.retriers[name].run(
            lambda: handle.http.remote(method, path, query, headers, client, root))

    @app.get("/scenes/{name}", include_in_schema=False)
    async def scene_root(self, name: str, request: Request) -> Response:
        if name not in self.scenes:
            return self._unknown(name, request)
        return RedirectResponse(f"/scenes/{name}/", status_code=308)

    @app.get("/scenes/{name}/metrics", summary="The scene's metrics: every replica's series, labelled "
             "replica, and the gateway's counters of the scene", response_class=Response)
    async def scene_metrics(self, name: str, request: Request) -> Response:
        # Asked of a replica first, so the scene's own token (or open_probes) decides who may read them.
        answer = await self.scene_route(name, "metrics", request)
        if answer.status_code != 200:
            return answer
        expositions, lost = await self.board.scene.remote(name)
        retrier = self.retriers[name]
        text = merge(expositions) + gateway_series(name, retries=retrier.retries, replicas=len(expositions),
                                                   stream_restarts=retrier.stream_restarts, lost=lost)
        return Response(text, media_type=answer.media_type or "text/plain; version=0.0.4",
                        headers={k: v for k, v in answer.headers.items()
                                 if k.lower() in (REPLICA_HEADER.lower(),)})

    @app.get("/scenes/{name}/openapi.json", include_in_schema=False)
    async def scene_openapi(self, name: str, request: Request) -> Response:
        """The scene's own schema (its replica's), its paths under the scene's prefix: the scene's
        /docs (served by the replica, pointed here) then tries its routes where they are."""
        answer = await self.scene_route(name, "openapi.json", request)
        if answer.status_code != 200:
            return answer
        schema = json.loads(answer.body)
        schema["paths"] = {f"/scenes/{name}{path}": ops for path, ops in schema.get("paths", {}).items()}
        schema.pop("servers", None)
        info = schema.setdefault("info", {})
        info["title"] = f"{info.get('title', 'edmcgs')}: scene {name}"
        return JSONResponse(schema)

    @app.api_route("/scenes/{name}/{path:path}", methods=["GET", "HEAD"],
                   summary="The scene's own API (see edmcgs-serve's /docs)")
    async def scene_route(self, name: str, path: str, request: Request) -> Response:
        if name not in self.scenes:
            return self._unknown(name, request)
        try:
            result = await self._http(name, request.method, "/" + path, request.url.query,
                                      list(request.headers.items()), _client(request))
        except BackPressureError:
            return _error(503, protocol.ErrorCode.BUSY, f"scene {name!r}: every replica's queue is full",
                          retry_after=True)
        except Exception as exc:
            if retryable(exc):
                return _error(503, protocol.ErrorCode.NOT_READY,
                              f"scene {name!r}: no replica answered ({type(exc).__name__})", True)
            raise
        headers = {k: v for k, v in result.headers if k.lower() != "content-type"}
        media = next((v for k, v in result.headers if k.lower() == "content-type"), None)
        return Response(result.body, status_code=result.status, headers=headers, media_type=media)

    def _unknown(self, name: str, request: Request) -> JSONResponse:
        """404 naming the scenes (a page of the gateway's own: its checks first)."""
        refused = self._auth(request)
        if refused is not None:
            return refused
        return _error(404, protocol.ErrorCode.INVALID_INPUT,
                      f"no scene named {name!r}; GET /scenes lists them: {', '.join(self.scenes)}")

    @app.websocket("/scenes/{name}/stream")
    async def stream(self, ws: WebSocket, name: str) -> None:
        if name not in self.scenes:  # the gateway answers: its Host rules (a scene's are its replica's)
            refused = foreign(ws.scope, self.allowed_hosts)
            if refused is not None:
                await ws.close(code=1008, reason=refused[:120])
                return
        await ws.accept()
        if name not in self.scenes:
            body = protocol.ErrorBody(protocol.ErrorCode.INVALID_INPUT, f"no scene named {name!r}")
            await ws.send_bytes(protocol.pack(body.to_message()))
            await ws.close(code=1008, reason="no such scene")
            return
        relay = StreamRelay(ws, self.scenes[name], self.retriers[name], _client(ws), self.mailbox)
        await relay.run()
