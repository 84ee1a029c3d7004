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

from edmcgs.server import errors
from edmcgs.server.middleware import AccessMiddleware
from edmcgs.server.routes import health, render, scene, stream
from edmcgs.server.service import Service
from edmcgs.server.settings import Settings

log = logging.getLogger("edmcgs.server")

DESCRIPTION = """Renders an EdMCGS dynamic scene at any time and pose while its event stream plays.

Time: `t` is seconds from the scene's start (`t_start_us` of `GET /scene`), `t_us` absolute microseconds
on the checkpoint's clock. Poses are camera-to-world, OpenCV convention. The wire schema (headers,
websocket messages, error bodies) is `edmcgs.protocol`. With `EDMCGS_TOKEN` set, every route
wants `Authorization: Bearer <token>` (or `?token=`).
"""


def _openapi(app: FastAPI, settings: Settings) -> dict:
    """FastAPI's schema with this server's own limits (the size caps come from the settings) and, with
    a token, the bearer scheme (so /docs can authorize its requests)."""
    if app.openapi_schema is None:
        from fastapi.openapi.utils import get_openapi

        schema = get_openapi(title=app.title, version=app.version, description=app.description,
                             routes=app.routes)
        caps = {"width": settings.max_width, "height": settings.max_height}
        for param in schema["paths"]["/render"]["get"].get("parameters", []):
            if param["name"] in caps:
                for option in param["schema"].get("anyOf", [param["schema"]]):
                    if option.get("type") == "integer":
                        option["maximum"] = caps[param["name"]]
        if settings.token is not None:
            schema.setdefault("components", {})["securitySchemes"] = {
                "bearer": {"type": "http", "scheme": "bearer"}}
            schema["security"] = [{"bearer": []}]
        app.openapi_schema = schema
    return app.openapi_schema


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

    app = FastAPI(title="edmcgs", version="0.1.0", description=DESCRIPTION, lifespan=lifespan)
    app.state.settings = settings
    token = settings.token.get_secret_value() if settings.token is not None else None
    open_paths = {"/docs", "/docs/oauth2-redirect", "/redoc", "/openapi.json"}  # the schema, not data
    if settings.open_probes:
        open_paths |= {"/healthz", "/metrics"}
    app.add_middleware(AccessMiddleware, token=token, allowed_hosts=settings.host_allowlist,
                       open_paths=frozenset(open_paths))
    errors.install(app)
    for module in (render, scene, health, stream):
        app.include_router(module.router, responses=render.AUTH_ERRORS)
    app.openapi = lambda: _openapi(app, settings)
    viewer = files("edmcgs.clients") / "viewer"
    if viewer.is_dir() and (viewer / "index.html").is_file():
        # The browser viewer: static files only, mounted last so the API routes take precedence.
        app.mount("/", StaticFiles(directory=str(viewer), html=True), name="viewer")
    return app
