"""GET /ply: the deformed Gaussians at a time as a 3DGS PLY file (``model/ply.py``, the layout of
``edmcgs export-ply``), for SuperSplat, gsplat's viewer or SIBR. Time as GET /render: the same
instant, the same events window [tau(t), t) from the ring, the same 416 outside what can be rendered.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import partial
from typing import Annotated

from fastapi import APIRouter, Depends
from fastapi.responses import Response

from edmcgs import protocol
from edmcgs.errors import EdmcgsError, RenderError
from edmcgs.model.ply import ply_bytes
from edmcgs.server.routes.render import ERRORS, ServiceDep, scene_time
from edmcgs.server.service import Service

router = APIRouter()

MEDIA_TYPE = "application/octet-stream"
HEADERS = (protocol.HEADER_T_US, protocol.HEADER_T, protocol.HEADER_ANCHOR_US, protocol.HEADER_EVENTS,
           protocol.HEADER_ANCHOR)
"""What a /ply response says of its instant (the same headers as GET /render's)."""


@dataclass(frozen=True)
class PlyFile:
    data: bytes
    headers: dict[str, str]
    filename: str


def export(service: Service, t_us: int | None) -> PlyFile:
    """Blocking (run on the render pool): the PLY of the Gaussians at ``t_us`` (None: the head)."""
    engine = service.engine
    instant = engine.resolve(t_us)
    try:
        state, events = engine.state(instant)
        data = ply_bytes(state)
    except EdmcgsError:
        raise
    except Exception as exc:  # torch failures: a 500 with a message, not a crash
        raise RenderError(f"PLY export failed: {type(exc).__name__}: {exc}") from exc
    t = engine.seconds_of(instant.t_us)
    headers = {protocol.HEADER_T_US: str(instant.t_us), protocol.HEADER_T: repr(t),
               protocol.HEADER_ANCHOR_US: str(instant.anchor_us), protocol.HEADER_EVENTS: str(events),
               protocol.HEADER_ANCHOR: engine.anchor_kind(instant)}
    return PlyFile(data, headers, f"edmcgs-t{t:.6f}.ply")


@router.get(
    "/ply", response_class=Response, summary="The Gaussians at time t as a 3DGS PLY file",
    description="The deformed Gaussians at t (the same instant and events window as GET /render) in "
                "the PLY layout of 3DGS (x y z, normals, f_dc / f_rest, opacity logit, log scales, "
                "rotation w x y z), as `edmcgs export-ply` writes it; SuperSplat, gsplat's viewer and SIBR "
                "read it. A checkpoint's distant background layer is not a set of Gaussians and is not "
                "in the file.",
    responses={200: {"content": {MEDIA_TYPE: {"schema": {"type": "string", "format": "binary"}}},
                     "description": "the PLY file (attachment); headers " + ", ".join(HEADERS)},
               **{s: ERRORS[s] for s in (416, 422, 503)}})
async def ply(service: ServiceDep, scene_t: Annotated[int | None, Depends(scene_time)]) -> Response:
    out = await service.pool.run(partial(export, service, scene_t))
    headers = {**out.headers, "Cache-Control": "no-store",
               "Content-Disposition": f'attachment; filename="{out.filename}"'}
    return Response(out.data, media_type=MEDIA_TYPE, headers=headers)
