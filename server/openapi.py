"""The app's OpenAPI document: FastAPI's, with this server's own limits (the size caps come from the
settings), the wire's schemas from ``edmcgs.protocol`` (``wire_schema``; every error response refers to
``ErrorBody``) and the bearer scheme of ``EDMCGS_TOKEN`` (the Authorize button of /docs).

It only documents: the token is enforced by ``middleware.AccessMiddleware`` alone.
"""

from __future__ import annotations

from fastapi import FastAPI
from fastapi.openapi.utils import get_openapi

from edmcgs.server import wire_schema
from edmcgs.server.settings import Settings

BEARER = "bearer"
"""The security scheme's name in the document."""


def bearer_scheme(token_set: bool) -> dict:
    """The bearer scheme, saying whether this server requires it."""
    state = ("This server has EDMCGS_TOKEN set: every route marked with a lock needs it."
             if token_set else "This server has no EDMCGS_TOKEN: no route needs a token.")
    return {"type": "http", "scheme": "bearer",
            "description": "`Authorization: Bearer <EDMCGS_TOKEN>`; where a header cannot be set (a "
                           "browser's page load or websocket) `?token=<EDMCGS_TOKEN>` is accepted too. "
                           + state}


def build(app: FastAPI, settings: Settings, open_paths: frozenset[str]) -> dict:
    """The document (computed once per app)."""
    if app.openapi_schema is not None:
        return app.openapi_schema
    schema = get_openapi(title=app.title, version=app.version, description=app.description,
                         routes=app.routes)
    caps = {"width": settings.max_width, "height": settings.max_height}
    for param in schema["paths"]["/render"]["get"].get("parameters", []):
        if param["name"] in caps:
            for option in param["schema"].get("anyOf", [param["schema"]]):
                if option.get("type") == "integer":
                    option["maximum"] = caps[param["name"]]
    components = schema.setdefault("components", {})
    components.setdefault("schemas", {}).update(wire_schema.schemas())
    token_set = settings.token is not None
    components["securitySchemes"] = {BEARER: bearer_scheme(token_set)}
    if token_set:
        for path, operations in schema["paths"].items():
            if path not in open_paths:
                for operation in operations.values():
                    operation["security"] = [{BEARER: []}]
    app.openapi_schema = schema
    return schema
