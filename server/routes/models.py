"""Models: register (a file in the data directory or an upload), upload, list,
inspect, delete (deferred while in use), and viewing tokens."""

from __future__ import annotations

import asyncio

from fastapi import APIRouter, Query, Request, Response
from fastapi.responses import JSONResponse
from pydantic import ValidationError

from vastray.camera import Vec3, parse_vec3
from vastray.schemas import (
    ModelCreated,
    ModelInfo,
    ModelPatch,
    ModelRequest,
    PartInfo,
    PartList,
    TokenInfo,
    TokenRequest,
    UploadInfo,
    describe_errors,
)
from vastray.server.app import State
from vastray.server.auth import credential
from vastray.server.deps import Admin, state_of
from vastray.server.errors import ApiError
from vastray.server.files import inside, kind_of
from vastray.server.routes.jobs import submit_build

router = APIRouter(prefix="/api", tags=["models"])


def parse_up(text: str) -> Vec3:
    """An up vector given as 'x,y,z' in a query, as a unit vector; 422 if it is none."""
    try:
        return ModelPatch(up=parse_vec3(text)).up  # type: ignore[return-value]
    except ValidationError as exc:
        raise ApiError(422, "invalid_request", describe_errors(exc.errors())) from None
    except ValueError as exc:
        raise ApiError(422, "invalid_request", f"up: {exc}") from None


def register(
    state: State,
    *,
    path: str | None,
    upload: str | None,
    name: str | None,
    options: object = None,
    up: Vec3 | None = None,
) -> ModelCreated:
    """A built model is served at once; a mesh starts the build that makes it."""
    file = state.uploads.path(upload) if upload is not None else inside(state.data_dir, path or "")
    label = name or file.stem
    if kind_of(file) == "model":
        row = state.store.register_file(file, label, move=upload is not None, up=up)
        if upload is not None:
            state.uploads.remove(upload)
        return ModelCreated(model=state.store.info(row))
    job = submit_build(state, source=path or "", name=name, options=options, upload=upload, up=up)  # type: ignore[arg-type]
    assert job.model_id is not None
    return ModelCreated(model=state.store.info(state.store.row(job.model_id)), job=job)


@router.post(
    "/models",
    status_code=201,
    summary="Register a built model or a mesh in the data directory, "
    "or an upload (a mesh starts a build job: 202)",
)
def create_model(body: ModelRequest, request: Request, response: Response, _: Admin) -> ModelCreated:
    created = register(
        state_of(request),
        path=body.path,
        upload=body.upload,
        name=body.name,
        options=body.options,
        up=body.up,
    )
    if created.job is not None:
        response.status_code = 202
    return created


@router.post("/uploads", status_code=201, summary="Upload a mesh or a built model (the raw file as the body)")
async def upload(
    request: Request,
    _: Admin,
    filename: str = Query(
        ..., min_length=1, max_length=255, description="the file's name (its type is read from it)"
    ),
    register_it: bool = Query(
        False, alias="register", description="register it at once (a mesh starts a build)"
    ),
    name: str | None = Query(None, max_length=200),
    up: str | None = Query(
        None, max_length=200, description="with register: which way is up in the model, 'x,y,z' (e.g. 0,0,1)"
    ),
) -> UploadInfo:
    state = state_of(request)
    # Refused before the upload is read.
    if up is not None and not register_it:
        raise ApiError(
            422, "invalid_request", "up goes with register=true (or with POST /api/models {upload, up})"
        )
    up_vector = parse_up(up) if up is not None else None
    length = request.headers.get("content-length")
    declared = int(length) if length and length.isdigit() else None
    upload_id, path = await state.uploads.receive(filename, request.stream(), declared)
    try:
        kind = kind_of(path)
    except ApiError:
        state.uploads.remove(upload_id)
        raise
    size = path.stat().st_size
    created = None
    if register_it:
        import asyncio

        created = await asyncio.to_thread(
            register, state, path=None, upload=upload_id, name=name, up=up_vector
        )
    return UploadInfo(id=upload_id, filename=path.name, bytes=size, kind=kind, created=created)  # type: ignore[arg-type]


@router.get("/models", summary="Models being built and ready (a viewing token sees its own model only)")
def list_models(request: Request) -> list[ModelInfo]:
    state = state_of(request)
    grant = state.auth.grant(credential(request))
    return [state.store.info(m) for m in state.registry.models() if grant.may_view_model(m.id)]


@router.get("/models/{model_id}", summary="Triangles, bounds, LOD levels, bytes, build parameters, part ids")
def get_model(model_id: str, request: Request) -> ModelInfo:
    state = state_of(request)
    state.auth.require_model_view(request, model_id)
    return state.store.info(state.store.row(model_id))


@router.patch("/models/{model_id}", summary="Rename a model, or say which way is up in it or its units")
async def patch_model(model_id: str, body: ModelPatch, request: Request, _: Admin) -> ModelInfo:
    state = state_of(request)
    row = await asyncio.to_thread(state.store.patch, model_id, name=body.name, up=body.up, units=body.units)
    info = state.store.info(row)
    # Pages open on the model take the new name, up and units at once (a review's
    # followers see the presenter's units); the stream's `model` event.
    event = {"type": "model", "model": model_id, "name": info.name, "up": list(info.up), "units": info.units}
    state.streams.announce(model_id, event)
    return info


@router.get("/models/{model_id}/parts", summary="Parts (name, bounds, triangles), searched by name")
def list_parts(
    model_id: str,
    request: Request,
    q: str = Query("", max_length=200, description="part names containing this, ignoring case"),
    ids: str = Query(
        "",
        max_length=20_000,
        description="comma-separated part ids: only these parts (unknown ids are left out), in table order",
    ),
    offset: int = Query(0, ge=0),
    limit: int = Query(1000, ge=1, le=20_000),
) -> PartList:
    state = state_of(request)
    state.auth.require_model_view(request, model_id)
    # The bounds of parts a view highlights that a page has not been sent (a welcome
    # lists the first WELCOME_PARTS), e.g. for a section box around them.
    wanted = _part_ids(ids) if ids else None
    with state.store.lease(model_id) as model:
        found = model.part_table.search(q)
    if wanted is not None:
        found = [p for p in found if p.id in wanted]
    return PartList(total=len(found), parts=[PartInfo.of(p) for p in found[offset : offset + limit]])


def _part_ids(text: str) -> set[int]:
    words = [w.strip() for w in text.split(",")]
    if not all(w.isascii() and w.isdigit() for w in words):
        example = "part ids are whole numbers, comma-separated (e.g. 7,12,40)"
        raise ApiError(422, "invalid_request", f"ids: {example}, not {text[:60]!r}")
    return {int(w) for w in words}


@router.delete(
    "/models/{model_id}",
    summary="Delete a model (deferred while a viewer, render or job uses it)",
    responses={202: {"description": "deferred until its users leave"}, 204: {"description": "deleted"}},
)
def delete_model(model_id: str, request: Request, _: Admin) -> Response:
    state = state_of(request)
    gone = state.store.delete(model_id)
    if gone:
        return Response(status_code=204)
    return JSONResponse({"status": "deleting", "in_use": state.store.in_use(model_id)}, 202)


@router.post("/models/{model_id}/tokens", status_code=201, summary="A viewing token for one model")
def create_token(model_id: str, body: TokenRequest, request: Request, _: Admin) -> TokenInfo:
    state = state_of(request)
    state.store.row(model_id)
    token, row = state.auth.issue("model", model_id, body.ttl_seconds, label=body.label)
    return TokenInfo(
        token=token, scope="model", subject=model_id, expires_at=row.expires_at, label=body.label
    )
