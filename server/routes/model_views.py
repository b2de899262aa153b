"""Views saved with a model, as CAD viewers keep viewpoints: a name, a camera, the
section planes and the highlighted parts. Anyone who may view the model lists them and
goes to them; saving and deleting need the API key. A review keeps its own saved views
(routes/reviews.py); these outlive reviews and go with the model."""

from __future__ import annotations

import asyncio
import secrets
from typing import Any

from fastapi import APIRouter, Request, Response
from pydantic import BaseModel, Field

from vastray.protocol import CameraState
from vastray.schemas import SectionPlane, Strict
from vastray.server.deps import Admin, state_of
from vastray.server.errors import ApiError
from vastray.server.views import camera_problem

router = APIRouter(prefix="/api/models/{model_id}/views", tags=["views"])

MAX_VIEWS_PER_MODEL = 500  # a flood of saves fills a model's list, not the disk


class ModelViewRequest(Strict):
    name: str = Field(min_length=1, max_length=200)
    camera: CameraState
    sections: list[SectionPlane] = Field(default_factory=list, max_length=6)
    highlight: list[int] = Field(default_factory=list, max_length=4096, description="part ids")


class ModelView(BaseModel):
    id: str
    name: str
    created_at: float
    camera: CameraState
    sections: list[SectionPlane] = []
    highlight: list[int] = []


class ModelViewList(BaseModel):
    views: list[ModelView]


def _view(row: dict[str, Any]) -> ModelView:
    return ModelView(id=row["id"], name=row["name"], created_at=row["created_at"], **row["state"])


@router.get("", summary="Views saved with a model, oldest first")
def list_views(model_id: str, request: Request) -> ModelViewList:
    state = state_of(request)
    state.auth.require_model_view(request, model_id)
    state.store.row(model_id)
    return ModelViewList(views=[_view(r) for r in state.registry.model_views(model_id)])


@router.post("", status_code=201, summary="Save a view with a model: name, camera, sections, highlight")
async def save_view(model_id: str, body: ModelViewRequest, request: Request, _: Admin) -> ModelView:
    state = state_of(request)
    await asyncio.to_thread(state.store.row, model_id, ready=True)
    problem = camera_problem(body.camera)
    if problem:
        raise ApiError(422, "invalid_camera", problem)
    view_id = f"view-{secrets.token_hex(6)}"
    kept = body.model_dump(exclude={"name"})
    kept["camera"]["seq"] = 0  # (a stream's sequence number means nothing once saved)
    added = await asyncio.to_thread(
        state.registry.add_model_view, view_id, model_id, body.name, kept, MAX_VIEWS_PER_MODEL
    )
    if added is None:
        message = f"model {model_id} has {MAX_VIEWS_PER_MODEL} saved views: delete some first"
        raise ApiError(409, "too_many_views", message)
    _announce(request, model_id)
    return _view(added)


@router.delete("/{view_id}", status_code=204, summary="Delete a view saved with a model")
async def delete_view(model_id: str, view_id: str, request: Request, _: Admin) -> Response:
    state = state_of(request)
    await asyncio.to_thread(state.store.row, model_id)
    if not await asyncio.to_thread(state.registry.delete_model_view, model_id, view_id):
        raise ApiError(404, "view_not_found", f"model {model_id} has no saved view {view_id!r}")
    _announce(request, model_id)
    return Response(status_code=204)


def _announce(request: Request, model_id: str) -> None:
    """Every page viewing the model lists its views again (the stream's `model_views`)."""
    state_of(request).streams.announce(model_id, {"type": "model_views", "model": model_id})
