"""Build jobs: submit, list, status, log, live progress (server-sent events), cancel."""

from __future__ import annotations

import asyncio
import json
import secrets
import time
from collections.abc import AsyncIterator
from pathlib import Path

from fastapi import APIRouter, Request
from fastapi.responses import PlainTextResponse, StreamingResponse

from vastray.build import INCORE_BYTES_PER_TRIANGLE, MIN_INCORE_TRIANGLES
from vastray.camera import Vec3
from vastray.layouts import LAYOUT_FLAGS, layout_options
from vastray.schemas import TERMINAL_JOB_STATES, BuildOptionsIn, JobInfo, JobRequest
from vastray.server.aio import ShutdownError, get_or_stop
from vastray.server.app import State
from vastray.server.deps import Admin, state_of
from vastray.server.errors import ApiError
from vastray.server.files import inside, kind_of
from vastray.server.registry import JobRow
from vastray.sources import parse_scene
from vastray.units import format_bytes, parse_bytes

router = APIRouter(prefix="/api/jobs", tags=["jobs"])
MIN_BUILD_MEMORY = MIN_INCORE_TRIANGLES * INCORE_BYTES_PER_TRIANGLE  # what build_model accepts
HEARTBEAT_SECONDS = 15.0  # keeps proxies from closing a quiet event stream


def resolve_source(state: State, source: str | None, upload: str | None) -> tuple[str, str]:
    """(what the builder reads, a name for it). ApiError for sources it cannot build."""
    if upload is not None:
        path = state.uploads.path(upload)
        return str(path), path.stem
    assert source is not None
    try:
        scene = parse_scene(source)
    except ValueError as exc:
        raise ApiError(422, "invalid_source", str(exc)) from None
    if scene is not None:
        return source, "demo" if source == "demo" else scene.label
    path = inside(state.data_dir, source)
    if kind_of(path) == "model":
        raise ApiError(
            422, "already_built", f"{source} is already a built model; register it with POST /api/models"
        )
    return str(path), Path(source).stem


def build_options(state: State, options: BuildOptionsIn | None) -> dict[str, int | float | bool]:
    s = state.settings
    memory = s.build_memory
    if options is not None and options.memory is not None:
        try:
            memory = parse_bytes(options.memory, "memory budget")
        except ValueError as exc:
            raise ApiError(422, "invalid_options", str(exc)) from None
    if memory < MIN_BUILD_MEMORY:
        raise ApiError(
            422,
            "invalid_options",
            f"memory budget too small: the builder needs at least {format_bytes(MIN_BUILD_MEMORY)}",
        )
    if memory > s.job_memory_limit:
        raise ApiError(
            422,
            "invalid_options",
            f"a memory budget of {format_bytes(memory)} is over this server's "
            f"limit of {format_bytes(s.job_memory_limit)} per job",
        )
    threads = s.build_threads if options is None or options.threads is None else options.threads
    opts: dict[str, int | float | bool] = {"memory": memory, "threads": threads}
    # The layout's options, then those the request names over them. Each is recorded
    # only when on (absent: off), as the model's options.
    chosen = layout_options(options.layout if options is not None else "balanced")
    if options is not None:
        for name in LAYOUT_FLAGS:
            value = getattr(options, name)
            if name in options.model_fields_set and value is not None:
                chosen[name] = value
    if chosen.get("quantized_splits", True):
        opts["quantized_splits"] = True
    if chosen.get("voxel_errors", True):
        opts["voxel_errors"] = True
    for name in ("quantized_vertices", "compact_triangles"):
        if chosen.get(name):
            opts[name] = True
    for name in ("tier_width", "traversal_cost"):
        if chosen.get(name) is not None:
            opts[name] = chosen[name]
    if chosen.get("lz4_hc_level"):
        opts["lz4_hc_level"] = chosen["lz4_hc_level"]
    return opts


def submit_build(
    state: State,
    *,
    source: str,
    name: str | None,
    options: BuildOptionsIn | None,
    upload: str | None = None,
    up: Vec3 | None = None,
) -> JobInfo:
    """Queues a build of `source` (or an upload) into a new model, listed as building."""
    reads, default_name = resolve_source(state, source if upload is None else None, upload)
    opts: dict[str, object] = dict(build_options(state, options))
    if up is not None:  # the file carries it too (the model's row is what the server goes by)
        opts["up"] = list(up)
    job_id = f"job-{secrets.token_hex(6)}"
    label = name or default_name
    model = state.store.reserve(label, source if upload is None else f"upload:{upload}", job_id, up)
    job = JobRow(
        job_id,
        "build",
        model.id,
        label,
        reads,
        "queued",
        None,
        0.0,
        None,
        None,
        None,
        opts,
        None,
        time.time(),
        None,
        None,
    )
    return state.jobs.submit(job)


def job_or_404(state: State, job_id: str) -> JobInfo:
    try:
        return state.jobs.info(job_id)
    except KeyError:
        raise ApiError(404, "job_not_found", f"no job {job_id!r}") from None


@router.post(
    "",
    status_code=202,
    summary="Build a model (from 'demo', 'scene:…', a file in the data directory, or an upload)",
)
def create_job(body: JobRequest, request: Request, _: Admin) -> JobInfo:
    return submit_build(
        state_of(request),
        source=body.source or "",
        name=body.name,
        options=body.options,
        upload=body.upload,
        up=body.up,
    )


@router.get("", summary="Jobs, newest first")
def list_jobs(request: Request, _: Admin, state: str | None = None) -> list[JobInfo]:
    s = state_of(request)
    states = tuple(state.split(",")) if state else None
    return [s.jobs.info(j.id) for j in s.registry.jobs(states)]


@router.get("/{job_id}", summary="State, phase, percent, ETA and log tail")
def get_job(job_id: str, request: Request, _: Admin) -> JobInfo:
    return job_or_404(state_of(request), job_id)


@router.get("/{job_id}/log", response_class=PlainTextResponse, summary="The job's log")
def get_log(job_id: str, request: Request, _: Admin) -> str:
    s = state_of(request)
    job_or_404(s, job_id)
    return "\n".join(s.registry.job_log(job_id)) + "\n"


@router.post("/{job_id}/cancel", summary="Cancel a queued or running job")
def cancel_job(job_id: str, request: Request, _: Admin) -> JobInfo:
    s = state_of(request)
    job_or_404(s, job_id)
    return s.jobs.cancel(job_id)


@router.get("/{job_id}/events", summary="Live progress as server-sent events (`progress`, then `end`)")
async def job_events(job_id: str, request: Request, _: Admin) -> StreamingResponse:
    s = state_of(request)
    await asyncio.to_thread(job_or_404, s, job_id)
    # Listen before taking the first snapshot, so no change falls between the two.
    queue = s.jobs.listen(job_id)
    first = await asyncio.to_thread(s.jobs.info, job_id)

    def event(kind: str, info: JobInfo) -> bytes:
        return f"event: {kind}\ndata: {json.dumps(info.model_dump())}\n\n".encode()

    async def stream() -> AsyncIterator[bytes]:
        try:
            yield event("progress", first)
            if first.state in TERMINAL_JOB_STATES:
                yield event("end", first)
                return
            while True:
                info = await get_or_stop(queue, s.stopping, HEARTBEAT_SECONDS)
                if info is None:
                    yield b": heartbeat\n\n"
                    continue
                if info.state in TERMINAL_JOB_STATES:
                    yield event("end", info)
                    return
                yield event("progress", info)
        except ShutdownError:
            yield b"event: shutdown\ndata: {}\n\n"
        finally:
            s.jobs.unlisten(queue, job_id)

    return StreamingResponse(
        stream(),
        media_type="text/event-stream",
        headers={"Cache-Control": "no-cache", "X-Accel-Buffering": "no"},
    )
