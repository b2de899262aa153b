"""One-shot renders and pick queries, at full detail unless asked otherwise."""

from __future__ import annotations

import json

from fastapi import APIRouter, Request, Response

from vastray.schemas import PickRequest, PickResponse, RenderRequest
from vastray.server.deps import state_of
from vastray.server.limits import client_key

router = APIRouter(prefix="/api/models/{model_id}", tags=["render"])


@router.post(
    "/render",
    summary="Render one image (PNG or JPEG), full detail by default, within a time limit",
    response_class=Response,
    responses={200: {"content": {"image/png": {}, "image/jpeg": {}}}},
)
async def render(model_id: str, body: RenderRequest, request: Request) -> Response:
    state = state_of(request)
    state.auth.require_model_view(request, model_id)
    state.rate.take(client_key(request))
    image = await state.renders.render_image(model_id, body)
    s = image.frame.stats
    headers = {
        "X-Vastray-Complete": "true" if image.frame.complete else "false",
        "X-Vastray-Frames": str(image.frame.frames),
        "X-Vastray-Render-Ms": f"{1000 * image.frame.seconds:.1f}",
        "X-Vastray-Encode-Ms": f"{image.encode_ms:.1f}",
        "X-Vastray-Stats": json.dumps(s.as_dict(), separators=(",", ":")),
        "Cache-Control": "no-store",
    }
    return Response(image.data, media_type=image.media_type, headers=headers)


@router.post("/pick", summary="Full-detail ray queries: position, distance, the input's triangle id, normal")
async def pick(model_id: str, body: PickRequest, request: Request) -> PickResponse:
    state = state_of(request)
    state.auth.require_model_view(request, model_id)
    state.rate.take(client_key(request))
    return await state.renders.pick(model_id, body)
