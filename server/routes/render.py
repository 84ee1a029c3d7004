"""GET /render: the scene at a time, from a pose, as PNG, JPEG or msgpack."""

from __future__ import annotations

import math
from functools import partial
from typing import Annotated, Literal

from fastapi import APIRouter, Depends, Header, Query, Request
from fastapi.responses import Response

from edmcgs import protocol
from edmcgs.geometry import parse_pose
from edmcgs.server.service import Service, invalid

router = APIRouter()

MAX_T_US = 2**62  # far beyond any clock, far inside int64: t_us arithmetic can never overflow

T_DOC = ("Scene time in seconds from the scene's start (`t_start_us` of GET /scene, its first anchor). "
         "Give `t` or `t_us`, not both; neither renders the live head of the event stream.")
T_US_DOC = ("Scene time in absolute microseconds, on the checkpoint's clock (Unix-epoch µs for a real "
            "camera): `t_us = t_start_us + round(t * 1e6)`.")
POSE_DOC = ("Camera-to-world pose, OpenCV convention (x right, y down, z forward): 16 numbers (row-major "
            "4x4) or 7 (tx,ty,tz,qw,qx,qy,qz: the quaternion's w FIRST; TUM trajectory files put it last, "
            "qx qy qz qw), comma-separated or a JSON array. Default: the event camera's own pose at t (the "
            "checkpoint's trajectory).")
SIZE_DOC = "Output {} in pixels (default: the camera's; one side alone keeps the aspect ratio; capped)."
FORMAT_DOC = "png (default), jpeg, or msgpack (a frame map with raw uint8 pixels); else from Accept."
MODE_DOC = (f"What the image shows: rgb (default); depth, the expected depth along the camera's z of each "
            f"pixel (sum w_i z_i / sum w_i over the splats blended into it), one grey channel, 255 at "
            f"{protocol.HEADER_DEPTH_NEAR} and 1 at {protocol.HEADER_DEPTH_FAR} (camera z in m: the 1st and "
            f"99th percentiles of the depths shown; nearer is brighter), 0 where the splats' opacity is "
            f"below {protocol.DEPTH_MIN_ALPHA:g}; alpha, the splats' accumulated opacity 1 - T, one grey "
            f"channel. Depth and alpha leave out a background layer and are never projected onto the events.")

ERROR_REF = {"$ref": "#/components/schemas/ErrorBody"}
"""The error body of every route, ``protocol.ErrorBody`` (its schema is added by ``server/openapi.py``)."""


def error(description: str) -> dict:
    return {"description": description, "content": {"application/json": {"schema": ERROR_REF}}}


ERRORS = {
    401: error("missing or wrong bearer token"),
    416: error("t cannot be rendered now; the body's valid_range says what can"),
    421: error("a Host or Origin this server does not answer to (EDMCGS_ALLOWED_HOSTS)"),
    422: error("a malformed parameter; the body's param names it"),
    500: error("the render failed; the service lives on"),
    503: error("render queue full (Retry-After) or not ready"),
}
AUTH_ERRORS = {401: ERRORS[401], 421: ERRORS[421], 500: ERRORS[500]}
"""What any route may answer besides its own."""


def parse_time(service: Service, t: float | None, t_us: int | None) -> int | None:
    """Scene µs from the query's ``t`` or ``t_us`` (None: the head); 422 naming the parameter."""
    if t is not None and t_us is not None:
        raise invalid("t", "give t (seconds from the scene's start) or t_us (absolute µs), not both")
    if t is not None:
        if not math.isfinite(t) or abs(t) > MAX_T_US / 1e6 / 2:
            raise invalid("t", f"t must be a finite number of seconds, got {t!r}")
        return service.engine.t_us_of_seconds(t)
    if t_us is not None and abs(t_us) > MAX_T_US:
        raise invalid("t_us", f"t_us={t_us} is outside any clock (|t_us| <= 2^62 µs)")
    return t_us


def parse_pose_param(pose: str | None):
    """c2w float64 [4, 4] from the ``pose`` query value, or None; PoseError (422) names ``pose``."""
    if pose is None:
        return None
    return parse_pose(protocol.parse_pose_text(pose), name="pose")


# The dependencies are ``async def`` though they never await: FastAPI runs a plain ``def`` dependency
# on a worker thread, a thread hop per dependency per request for a few microseconds of work.
async def get_service(request: Request) -> Service:
    """The running service (built by the app's lifespan)."""
    return request.app.state.service


ServiceDep = Annotated[Service, Depends(get_service)]


MAX_T_S = MAX_T_US / 1e6 / 2


async def scene_time(
    service: ServiceDep,
    t: Annotated[float | None, Query(description=T_DOC, ge=-MAX_T_S, le=MAX_T_S)] = None,
    t_us: Annotated[int | None, Query(description=T_US_DOC, ge=-MAX_T_US, le=MAX_T_US)] = None,
) -> int | None:
    """The query's time as scene µs (None: the head)."""
    return parse_time(service, t, t_us)


async def pose_query(pose: Annotated[str | None, Query(description=POSE_DOC,
                                                      max_length=protocol.MAX_POSE_TEXT)] = None):
    """The query's pose, c2w float64 [4, 4], or None."""
    return parse_pose_param(pose)


@router.get(
    "/render", response_class=Response, summary="Render the scene at time t from a pose",
    responses={200: {"content": {media: {"schema": {"type": "string", "format": "binary"}}
                                 for media in protocol.MEDIA_TYPES.values()},
                     "description": "the image; headers " + ", ".join(protocol.HEADERS) + " (and for "
                                    f"mode=depth {protocol.HEADER_DEPTH_NEAR}, {protocol.HEADER_DEPTH_FAR})"},
                **ERRORS})
async def render(
    service: ServiceDep,
    scene_t: Annotated[int | None, Depends(scene_time)],
    c2w: Annotated[object, Depends(pose_query)],
    width: Annotated[int | None, Query(description=SIZE_DOC.format("width"), ge=1)] = None,
    height: Annotated[int | None, Query(description=SIZE_DOC.format("height"), ge=1)] = None,
    format: Annotated[Literal["png", "jpeg", "msgpack"] | None, Query(description=FORMAT_DOC)] = None,
    mode: Annotated[Literal["rgb", "depth", "alpha"], Query(description=MODE_DOC)] = "rgb",
    accept: Annotated[str | None, Header(include_in_schema=False)] = None,
) -> Response:
    w, h = service.size(width, height)
    fmt = format or protocol.negotiate_format(accept)
    frame = await service.pool.run(partial(service.render_frame, scene_t, c2w, w, h,
                                           "raw" if fmt == "msgpack" else fmt, mode))
    service.metrics.render.labels("http").observe(frame.meta.render_ms / 1e3)
    headers = {**frame.meta.headers(), "Cache-Control": "no-store"}
    body = protocol.pack(frame.meta.to_message(frame.data)) if fmt == "msgpack" else frame.data
    return Response(body, media_type=protocol.MEDIA_TYPES[fmt], headers=headers)
