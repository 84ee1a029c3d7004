"""The FastAPI app factory. Nothing happens at import: ``create_app(settings)`` builds an app whose
lifespan loads the checkpoint, opens the event source, warms the renderer up and starts ingesting;
on shutdown it stops the ingest thread (joined), closes the source and the render pool.
"""

from __future__ import annotations

import asyncio
import logging
from contextlib import asynccontextmanager
from importlib.resources import files

from fastapi import FastAPI
from fastapi.staticfiles import StaticFiles

from edmcgs.server import docs, errors, openapi
from edmcgs.server.middleware import AccessMiddleware
from edmcgs.server.routes import events, health, ply, render, scene, stream
from edmcgs.server.service import Service
from edmcgs.server.settings import Settings

log = logging.getLogger("edmcgs.server")

DESCRIPTION = """Renders an EdMCGS dynamic scene at any time and pose while its event stream plays.

Time: `t` is seconds from the scene's start (`t_start_us` of `GET /scene`), `t_us` absolute microseconds
on the checkpoint's clock. Poses are camera-to-world, OpenCV convention. The wire schema (headers,
websocket messages, error bodies) is `edmcgs.protocol`. With `EDMCGS_TOKEN` set, every route
wants `Authorization: Bearer <token>` (or `?token=`): the Authorize button.

The websocket `WS /stream` (frames pushed live or over a time range): [its protocol](asyncapi), also as
an AsyncAPI document, [asyncapi.json](asyncapi.json).
"""


def create_app(settings: Settings | None = None, *, service_factory=Service.open) -> FastAPI:
    """The service as an ASGI app. ``settings``: default ``Settings()`` (the environment).

    ``service_factory(settings) -> Service`` opens the service in the lifespan (blocking, run in a thread).
    """
    settings = Settings() if settings is None else settings

    @asynccontextmanager
    async def lifespan(app: FastAPI):
        service = await asyncio.to_thread(service_factory, settings)
        service.start(asyncio.get_running_loop())
        app.state.service = service
        log.info("edmcgs-serve ready")
        try:
            yield
        finally:
            await asyncio.to_thread(service.close)
            log.info("edmcgs-serve stopped: ingest thread joined, source closed")

    app = FastAPI(title="edmcgs", version="0.1.0", description=DESCRIPTION, lifespan=lifespan,
                  docs_url=None, redoc_url=None)  # docs.install serves them without a CDN
    app.state.settings = settings
    token = settings.token.get_secret_value() if settings.token is not None else None
    open_paths = set(docs.install(app, settings))  # the docs and the schema, not data
    if settings.open_probes:
        open_paths |= {"/healthz", "/metrics"}
    app.add_middleware(AccessMiddleware, token=token, allowed_hosts=settings.host_allowlist,
                       open_paths=frozenset(open_paths), max_in_flight=settings.max_connections)
    errors.install(app)
    for module in (render, events, scene, health, stream, ply):
        app.include_router(module.router, responses=render.AUTH_ERRORS)
    app.openapi = lambda: openapi.build(app, settings, frozenset(open_paths))
    viewer = files("edmcgs.clients") / "viewer"
    if viewer.is_dir() and (viewer / "index.html").is_file():
        # The browser viewer: static files only, mounted last so the API routes take precedence.
        app.mount("/", StaticFiles(directory=str(viewer), html=True), name="viewer")
    return app
