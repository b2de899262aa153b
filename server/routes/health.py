"""Liveness, readiness and metrics; `/` for people."""

from __future__ import annotations

import time
from importlib import resources
from pathlib import Path

from fastapi import APIRouter, Request
from fastapi.responses import FileResponse, JSONResponse, Response
from prometheus_client import CONTENT_TYPE_LATEST

from vastray import __version__, native
from vastray.server.deps import state_of

router = APIRouter(tags=["health"])
WEB = Path(str(resources.files("vastray.client") / "web"))


@router.get("/healthz", summary="The process is up")
def healthz() -> dict[str, str]:
    return {"status": "ok"}


@router.get("/readyz", summary="The server can serve: registry open, cache up, not shutting down")
def readyz(request: Request) -> JSONResponse:
    state = state_of(request)
    if state.stopping.is_set():
        return JSONResponse({"status": "shutting down"}, 503)
    totals = state.store.cache.totals()
    counts = state.registry.job_counts()
    return JSONResponse(
        {
            "status": "ready",
            "version": __version__,
            "uptime_seconds": time.time() - state.started_at,
            "models_ready": len([m for m in state.registry.models(("ready",))]),
            "jobs_running": counts.get("running", 0),
            "jobs_queued": counts.get("queued", 0),
            "cache_budget_bytes": totals["budget_bytes"],
            "cache_resident_bytes": totals["resident_bytes"],
            "render_threads": state.settings.render_threads or native.hardware_threads(),
            "registry_schema": state.registry.schema_version,
        }
    )


@router.get("/metrics", summary="Prometheus text exposition", response_class=Response)
def metrics(request: Request) -> Response:
    return Response(state_of(request).metrics.render(), media_type=CONTENT_TYPE_LATEST)


@router.get("/", include_in_schema=False)
def index() -> FileResponse:
    """The viewer page (client/web); it reads the key or token from its own URL."""
    return FileResponse(WEB / "index.html", headers={"Cache-Control": "no-cache"})
