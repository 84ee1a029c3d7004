"""GET /healthz (ready or 503) and GET /metrics (Prometheus text)."""

from __future__ import annotations

from fastapi import APIRouter, Request
from fastapi.responses import JSONResponse, PlainTextResponse

from edmcgs.server.metrics import CONTENT_TYPE
from edmcgs.server.responses import Health

router = APIRouter()


@router.get("/healthz", summary="200 when the model is loaded and the event source delivers (no "
                               "sensor: once loaded); else 503", response_model=Health,
            responses={503: {"model": Health, "description": "not ready (Retry-After); the body says why"}})
async def healthz(request: Request) -> JSONResponse:
    ready, details = request.app.state.service.health()
    return JSONResponse(details, status_code=200 if ready else 503,
                        headers=None if ready else {"Retry-After": "1"})


@router.get("/metrics", response_class=PlainTextResponse, summary="Prometheus metrics (text format 0.0.4)")
async def metrics(request: Request) -> PlainTextResponse:
    return PlainTextResponse(request.app.state.service.metrics.exposition(), media_type=CONTENT_TYPE)
