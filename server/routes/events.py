"""GET /events: the event map I_E of a render's window, as a DV-style PNG or as msgpack counts."""

from __future__ import annotations

from functools import partial
from typing import Annotated, Literal

from fastapi import APIRouter, Depends, Header, Query
from fastapi.responses import Response

from edmcgs import protocol
from edmcgs.server.routes.render import ERRORS, ServiceDep, scene_time

router = APIRouter()

FORMAT_DOC = ("png (default): RGBA at the event sensor's size, positive sums blue, negative red, "
              "transparent where zero; msgpack: the signed sums (an event-map map); else from Accept.")

EVENT_MAP_SCHEMA = {
    "type": "object", "title": "EventMap", "required": list(protocol.EVENT_MAP_KEYS),
    "properties": {
        "type": {"type": "string", "enum": ["event_map"]},
        "t_us": {"type": "integer", "description": "the window's end (exclusive): the time a render shows"},
        "t": {"type": "number", "description": "the same, seconds from the scene's start"},
        "anchor_us": {"type": "integer", "description": "tau(t): the window's start (inclusive)"},
        "events": {"type": "integer", "description": "events in the window"},
        "width": {"type": "integer"}, "height": {"type": "integer"},
        "dtype": {"type": "string", "enum": [protocol.EVENT_MAP_DTYPE]},
        "data": {"type": "string", "format": "binary",
                 "description": "signed polarity sum per pixel, [height, width] row-major"},
    },
}
"""The msgpack body (``protocol.EventMapMeta.to_message``), as JSON Schema."""

HEADERS_DOC = {name: {"schema": {"type": "number" if name == protocol.HEADER_T else "integer"}}
               for name in protocol.EVENT_HEADERS}


@router.get(
    "/events", response_class=Response,
    summary="The event map I_E of the window a render at time t uses ([tau(t), t))",
    description=("The events the model's event branch sees for a render at t, summed per pixel with "
                 "their polarity. The same time rules and errors as GET /render; the headers say the "
                 "window (`X-Edmcgs-Anchor-Us` .. `X-Edmcgs-T-Us`) and its event count."),
    responses={200: {"content": {"image/png": {}, "application/msgpack": {"schema": EVENT_MAP_SCHEMA}},
                     "headers": HEADERS_DOC,
                     "description": "the event map; headers " + ", ".join(protocol.EVENT_HEADERS)},
               **{s: ERRORS[s] for s in (416, 422, 503)}})
async def events(
    service: ServiceDep,
    scene_t: Annotated[int | None, Depends(scene_time)],
    format: Annotated[Literal["png", "msgpack"] | None, Query(description=FORMAT_DOC)] = None,
    accept: Annotated[str | None, Header(include_in_schema=False)] = None,
) -> Response:
    fmt = format or ("msgpack" if protocol.negotiate_format(accept) == "msgpack" else "png")
    meta, body = await service.pool.run(partial(service.event_map, scene_t, fmt))
    headers = {**meta.headers(), "Cache-Control": "no-store"}
    return Response(body, media_type=protocol.MEDIA_TYPES[fmt], headers=headers)
