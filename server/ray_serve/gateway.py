"""The gateway: Serve's FastAPI ingress. ``/scenes`` lists the scenes; ``/scenes/{name}/...`` is that
scene's API, the very routes of ``edmcgs-serve`` (``/render``, ``/scene``, ``/healthz``, ``/metrics``,
``/stream``, the viewer at ``/scenes/{name}/``), answered by one of its replicas.

A call that fails because its replica died is sent again (``retry.py``): the client sees the answer of
a live replica, never the death. A websocket is relayed: the client's messages are kept, and the
replica-side session is (re)started from them, so a stream survives its replica too (its ``seq``
starts over). A new client message also restarts the replica-side session with every message so far
(a sweep then starts over from its ``t0``): a session is pinned to no replica.
"""


import asyncio
import contextlib
import html
import json
import logging
import time

from fastapi import FastAPI, Request, WebSocket
from fastapi.responses import HTMLResponse, JSONResponse, RedirectResponse, Response
from ray import serve
from ray.serve.exceptions import BackPressureError
from starlette.websockets import WebSocketDisconnect

from edmcgs import protocol
from edmcgs.server.ray_serve.asgi import WsMessage
from edmcgs.server.ray_serve.retry import Retrier, retryable

log = logging.getLogger("edmcgs.server.ray")

HEALTH_TIMEOUT_S = 5.0
"""How long ``/scenes`` waits for a scene's health before reporting it unknown."""
MAX_HISTORY = 256
"""Client messages a relayed stream keeps (each a partial subscription; older ones are folded in by
the replica already, but a restart replays only these)."""

app = FastAPI(title="edmcgs on Ray Serve", version="0.1.0",
              description="Many scenes: GET /scenes lists them; each scene's API (the one of "
                          "edmcgs-serve) lives under /scenes/{name}/.")


def _error(status: int, code: protocol.ErrorCode, detail: str, retry_after: bool = False) -> JSONResponse:
    return JSONResponse(protocol.ErrorBody(code, detail).to_message(), status_code=status,
                        headers={"Retry-After": "1"} if retry_after else None)


def _client(request_or_ws) -> str:
    client = request_or_ws.client
    return client.host if client is not None else "127.0.0.1"


@serve.ingress(app)
class Gateway:
    """``scenes``: name -> the scene deployment's handle; ``info``: name -> what ``/scenes`` says of it."""

    def __init__(self, scenes: dict, info: dict[str, dict]):
        self.scenes = scenes
        self.info = info
        self.retrier = Retrier()

    # ------------------------------------------------------------------ index
    async def _health(self, name: str) -> dict:
        try:
            result = await asyncio.wait_for(self._http(name, "GET", "/healthz", "", [("host", "localhost")]),
                                            HEALTH_TIMEOUT_S)
            return json.loads(result.body)
        except Exception as exc:
            return {"ready": False, "source": "unknown", "source_error": f"{type(exc).__name__}: {exc}"}

    @app.get("/scenes", summary="The scenes served, each with its health")
    async def list_scenes(self) -> dict:
        names = list(self.scenes)
        healths = await asyncio.gather(*(self._health(n) for n in names))
        return {"scenes": [{**self.info[n], "url": f"/scenes/{n}/", "health": h}
                           for n, h in zip(names, healths, strict=True)]}

    @app.get("/healthz", summary="200 while the gateway serves; each scene's readiness in the body")
    async def healthz(self) -> dict:
        names = list(self.scenes)
        healths = await asyncio.gather(*(self._health(n) for n in names))
        return {"ready": True, "retries": self.retrier.retries,
                "scenes": {n: bool(h.get("ready")) for n, h in zip(names, healths, strict=True)}}

    @app.get("/", response_class=HTMLResponse, include_in_schema=False)
    async def index(self) -> HTMLResponse:
        """Pick a scene: each link opens the browser viewer on that scene."""
        items = "".join(f'<li><a href="scenes/{html.escape(n)}/">{html.escape(n)}</a> — '
                        f'{html.escape(str(self.info[n].get("checkpoint")))}</li>' for n in self.scenes)
        return HTMLResponse(f"<!doctype html><meta charset=utf-8><title>edmcgs scenes</title>"
                            f"<h1>edmcgs scenes</h1><ul>{items}</ul>")

    # ------------------------------------------------------------------ one scene
    async def _http(self, name: str, method: str, path: str, query: str, headers: list, client: str
                    = "127.0.0.1"):
        handle = self.scenes[name]
        return await self.retrier.run(lambda: handle.http.remote(method, path, query, headers, client))

    @app.get("/scenes/{name}", include_in_schema=False)
    async def scene_root(self, name: str) -> Response:
        if name not in self.scenes:
            return self._unknown(name)
        return RedirectResponse(f"/scenes/{name}/", status_code=308)

    @app.api_route("/scenes/{name}/{path:path}", methods=["GET", "HEAD"],
                   summary="The scene's own API (see edmcgs-serve's /docs)")
    async def scene_route(self, name: str, path: str, request: Request) -> Response:
        if name not in self.scenes:
            return self._unknown(name)
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

    def _unknown(self, name: str) -> JSONResponse:
        return _error(404, protocol.ErrorCode.INVALID_INPUT,
                      f"no scene named {name!r}; GET /scenes lists them: {', '.join(self.scenes)}")

    @app.websocket("/scenes/{name}/stream")
    async def stream(self, ws: WebSocket, name: str) -> None:
        await ws.accept()
        if name not in self.scenes:
            body = protocol.ErrorBody(protocol.ErrorCode.INVALID_INPUT, f"no scene named {name!r}")
            await ws.send_bytes(protocol.pack(body.to_message()))
            await ws.close(code=1008, reason="no such scene")
            return
        relay = StreamRelay(ws, self.scenes[name], self.retrier, _client(ws))
        await relay.run()


class StreamRelay:
    """One client's websocket relayed to a scene (see the module docstring)."""

    def __init__(self, ws: WebSocket, handle, retrier: Retrier, client: str):
        self.ws, self.handle, self.retrier, self.client = ws, handle, retrier, client
        self.history: list[bytes | str] = []
        self.replies = 0  # control replies (subscribed / error) the client has had, one per message
        self.inbox: asyncio.Queue = asyncio.Queue()
        self.delivered = False  # a message reached the client since the last look
        self.query = ws.url.query
        self.headers = list(ws.headers.items())

    async def _read(self) -> None:
        try:
            while True:
                message = await self.ws.receive()
                if message["type"] == "websocket.disconnect":
                    break
                data = message.get("bytes") if message.get("bytes") is not None else message.get("text")
                if data is not None:
                    await self.inbox.put(data)
        finally:
            await self.inbox.put(None)

    async def _pump(self) -> WsMessage | None:
        """One replica-side session: forward what it sends; return its close (None: it just ended)."""
        skip = self.replies
        gen = self.handle.options(stream=True).stream.remote("/stream", self.query, self.headers,
                                                             list(self.history), self.client)
        try:
            async for item in gen:
                if item.close is not None:
                    return item
                if skip and item.bytes is not None:
                    kind = protocol.unpack(item.bytes).get("type")
                    if kind in ("subscribed", "error"):
                        skip -= 1
                        continue  # the reply to a replayed message: the client had it already
                await self._send(item)
        finally:
            gen.cancel()
        return None

    async def _send(self, item: WsMessage) -> None:
        self.delivered = True
        if item.bytes is not None:
            if len(item.bytes) < 4096 and protocol.unpack(item.bytes).get("type") in ("subscribed", "error"):
                self.replies += 1
            await self.ws.send_bytes(item.bytes)
        elif item.text is not None:
            await self.ws.send_text(item.text)

    async def run(self) -> None:
        reader = asyncio.create_task(self._read())
        pump: asyncio.Task | None = None
        failing_since: float | None = None  # replicas dying since then, none answering
        try:
            while True:
                if pump is None:
                    pump = asyncio.create_task(self._pump())
                getter = asyncio.create_task(self.inbox.get())
                done, _ = await asyncio.wait({pump, getter}, return_when=asyncio.FIRST_COMPLETED)
                if getter in done:
                    data = getter.result()
                    if data is None:  # the client went away
                        return
                    self.history = [*self.history, data][-MAX_HISTORY:]
                    pump.cancel()
                    with contextlib.suppress(BaseException):
                        await pump
                    if pump.done() and not pump.cancelled() and pump.exception() is None \
                            and pump.result() is not None:
                        await self._close(pump.result())
                        return
                    pump = None
                    continue
                getter.cancel()
                exc = pump.exception()
                if self.delivered:
                    failing_since, self.delivered = None, False
                if exc is None:
                    closing = pump.result()
                    await self._close(closing or WsMessage(close=1000))
                    return
                if not retryable(exc):
                    raise exc
                if failing_since is None:
                    failing_since = time.monotonic()
                elif time.monotonic() - failing_since > self.retrier.retry_for_s:
                    await self._close(WsMessage(close=1011, reason="no replica of the scene answers"))
                    return
                self.retrier.retries += 1
                log.warning("stream: its replica died (%s); restarting the session", type(exc).__name__)
                await asyncio.sleep(0.05)
                pump = None
        except WebSocketDisconnect:
            return
        finally:
            reader.cancel()
            if pump is not None and not pump.done():
                pump.cancel()
                with contextlib.suppress(BaseException):
                    await pump

    async def _close(self, item: WsMessage) -> None:
        with contextlib.suppress(Exception):
            await self.ws.close(code=item.close or 1000, reason=item.reason)
