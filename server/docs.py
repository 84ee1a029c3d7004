"""The API docs, served by the app itself with no internet: Swagger UI at /docs and ReDoc at /redoc with
their scripts and styles from the ``fastapi-offline`` package (a packaged copy of the swagger-ui-dist and
redoc bundles, under /docs/assets/), and the websocket protocol at /asyncapi.json and /asyncapi.

FastAPI's own /docs and /redoc load their assets from a CDN: the app is built without them
(``docs_url=None, redoc_url=None``) and ``install`` adds these.
"""

from __future__ import annotations

from importlib.resources import files

from fastapi import FastAPI, Request
from fastapi.openapi.docs import get_redoc_html, get_swagger_ui_html, get_swagger_ui_oauth2_redirect_html
from fastapi.responses import HTMLResponse, JSONResponse
from fastapi.staticfiles import StaticFiles

from edmcgs.server import asyncapi
from edmcgs.server.settings import Settings

ASSETS_URL = "/docs/assets"
ASSET_FILES = ("swagger-ui-bundle.js", "swagger-ui.css", "redoc.standalone.js", "favicon.png")
"""What the pages load, all from ``ASSETS_URL``."""
SWAGGER_PARAMETERS = {"validatorUrl": None}  # Swagger UI would otherwise send the schema to its validator
CSP = ("default-src 'self'; script-src 'self' 'unsafe-inline'; style-src 'self' 'unsafe-inline'; "
       "img-src 'self' data:; font-src 'self' data:; worker-src 'self' blob:; connect-src 'self'")
"""The docs pages' Content-Security-Policy: everything from this server. The bundles name a few outside
URLs of their own (ReDoc's footer logo on a CDN): the browser never asks for them."""


def _own_only(page: HTMLResponse) -> HTMLResponse:
    page.headers["Content-Security-Policy"] = CSP
    return page


def assets_dir() -> str:
    """The folder of the packaged Swagger UI and ReDoc bundles; a clear error when it is missing."""
    try:
        folder = files("fastapi_offline") / "static"
    except ModuleNotFoundError:
        raise RuntimeError("the API docs need the fastapi-offline package (a dependency of edmcgs: "
                           "reinstall with scripts/bootstrap.sh)") from None
    missing = [name for name in ASSET_FILES if not (folder / name).is_file()]
    if missing:
        raise RuntimeError(f"fastapi-offline ships no {', '.join(missing)} in {folder}")
    return str(folder)


def install(app: FastAPI, settings: Settings) -> frozenset[str]:
    """Add the docs routes and assets to ``app``; returns their paths (they need no token: the docs
    describe the API and hold no data)."""
    app.mount(ASSETS_URL, StaticFiles(directory=assets_dir()), name="docs-assets")
    redirect = app.swagger_ui_oauth2_redirect_url

    def urls(request: Request) -> tuple[str, str]:
        root = request.scope.get("root_path", "").rstrip("/")
        return root, f"{root}{app.openapi_url}"

    @app.get("/docs", include_in_schema=False)
    async def swagger(request: Request) -> HTMLResponse:
        root, openapi_url = urls(request)
        return _own_only(get_swagger_ui_html(
            openapi_url=openapi_url, title=f"{app.title}: Swagger UI",
            oauth2_redirect_url=f"{root}{redirect}",
            swagger_js_url=f"{root}{ASSETS_URL}/swagger-ui-bundle.js",
            swagger_css_url=f"{root}{ASSETS_URL}/swagger-ui.css",
            swagger_favicon_url=f"{root}{ASSETS_URL}/favicon.png",
            swagger_ui_parameters=SWAGGER_PARAMETERS))

    @app.get(redirect, include_in_schema=False)
    async def swagger_redirect() -> HTMLResponse:
        return get_swagger_ui_oauth2_redirect_html()

    @app.get("/redoc", include_in_schema=False)
    async def redoc(request: Request) -> HTMLResponse:
        root, openapi_url = urls(request)
        return _own_only(get_redoc_html(
            openapi_url=openapi_url, title=f"{app.title}: ReDoc",
            redoc_js_url=f"{root}{ASSETS_URL}/redoc.standalone.js",
            redoc_favicon_url=f"{root}{ASSETS_URL}/favicon.png", with_google_fonts=False))

    document = asyncapi.document(settings, app.version)

    @app.get("/asyncapi.json", include_in_schema=False)
    async def asyncapi_json() -> JSONResponse:
        return JSONResponse(document)

    page = asyncapi.page(document)

    @app.get("/asyncapi", include_in_schema=False)
    async def asyncapi_page() -> HTMLResponse:
        return _own_only(HTMLResponse(page))

    return frozenset({"/docs", redirect, "/redoc", app.openapi_url, "/asyncapi.json", "/asyncapi",
                      *(f"{ASSETS_URL}/{name}" for name in ASSET_FILES)})
