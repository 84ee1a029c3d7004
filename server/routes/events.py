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

MSGPACK_DOC = ("a msgpack map: type \"event_map\", t_us (the window's end, exclusive: the time a render "
               "shows), t, anchor_us (tau(t), the window's start), events (in the window), width, height "
               "(the event sensor's), dtype \"" + protocol.EVENT_MAP_DTYPE + "\" and data (bytes: the "
               "signed polarity sum per pixel, [height, width] row-major); protocol.EVENT_MAP_KEYS")
BODIES = {"image/png": {"schema": {"type": "string", "format": "binary",
                                   "description": "RGBA at the event sensor's size: ON blue, OFF red"}},
          "application/msgpack": {"schema": {"type": "string", "format": "binary",
                                             "description": MSGPACK_DOC}}}
"""The two bodies: bytes, as every binary body of this API (a msgpack map is no JSON)."""

HEADERS_DOC = {name: {"schema": {"type": "number" if name == protocol.HEADER_T else "integer"}}
               for name in protocol.EVENT_HEADERS}


@router.get(
    "/events", response_class=Response,
    summary="The event map I_E of the window a render at time t uses ([tau(t), t))",
    description=("The events the model's event branch sees for a render at t, summed per pixel with "
                 "their polarity. The same time rules and errors as GET /render; the headers say the "
                 "window (`X-Edmcgs-Anchor-Us` .. `X-Edmcgs-T-Us`) and its event count."),
    responses={200: {"content": BODIES,
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
