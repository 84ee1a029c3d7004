"""GET /scene: what the service serves (span, anchors, camera, trajectory, what can be rendered now)."""

from __future__ import annotations

from fastapi import APIRouter, Request

from edmcgs.server.responses import Scene

router = APIRouter()


@router.get("/scene", response_model=Scene,
            summary="The scene: time span, anchors, intrinsics, trajectory, live head")
async def scene(request: Request) -> dict:
    """Times are absolute µs on the checkpoint's clock (`*_us`) or seconds from `t_start_us` (`t`, `head_t`).

    `renderable` is the most recent interval of time GET /render accepts now (`renderable_ranges`: all
    of them, oldest first); `head_us` is the live head, the newest time whose events have all arrived.

    `tau_sources` says where tau(t), the anchor of each render's events window [tau, t), comes from, by
    range of scene time (`{"source", "t_us_min", "t_us_max", "t_min", "t_max"}`, inclusive): within
    the checkpoint's span, `"checkpoint"`: its own anchors (`anchors_us`), the windows it was trained on,
    even when the stream carries more frames; a stream's frames (`"stream"`) only where the checkpoint
    has no anchor.
    """
    return request.app.state.service.scene()
