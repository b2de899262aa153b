"""The FastAPI application: what the server holds (registry, model store, render
service, job manager, metrics) and its lifespan. Routes live in routes/."""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from fastapi import FastAPI
from fastapi.middleware.cors import CORSMiddleware
from fastapi.staticfiles import StaticFiles

from vastray import __version__
from vastray.server import errors
from vastray.server.auth import Auth
from vastray.server.files import Uploads
from vastray.server.jobs import JobManager
from vastray.server.limits import BodyLimit, RateLimiter
from vastray.server.metrics import Metrics
from vastray.server.model_store import ModelStore
from vastray.server.registry import Registry
from vastray.server.render_service import RenderService
from vastray.server.settings import Settings

log = logging.getLogger("vastray.server")


@dataclass
class State:
    """Everything a request may need, in one place (app.state.vastray)."""

    settings: Settings
    data_dir: Path
    registry: Registry
    auth: Auth
    store: ModelStore
    renders: RenderService
    jobs: JobManager
    uploads: Uploads
    metrics: Metrics
    rate: RateLimiter
    started_at: float = field(default_factory=time.time)
    # Set when shutdown begins (before uvicorn waits for open connections), so
    # long-lived responses (event streams, viewers) end at once.
    stopping: asyncio.Event = field(default_factory=asyncio.Event)
    viewers: int = 0
    streams: Any = None  # the StreamHub (stream.py), made with the state


def build_state(settings: Settings) -> State:
    data_dir = settings.data_dir.resolve()
    data_dir.mkdir(parents=True, exist_ok=True)
    registry = Registry(data_dir)
    done = registry.reconcile(data_dir)
    for what, items in done.items():
        for item in items:
            log.warning("registry at start: %s %s", what, item)
    metrics = Metrics()
    store = ModelStore(registry, data_dir, cache_bytes=settings.cache, fetchers=settings.fetchers)
    renders = RenderService(
        store,
        workers=settings.render_workers,
        threads=settings.render_threads,
        max_pixels=settings.max_pixels,
        max_timeout=settings.render_timeout,
        metrics=metrics,
    )
    jobs = JobManager(
        registry,
        data_dir,
        concurrency=settings.build_jobs,
        rss_slack=settings.build_rss_slack,
        publish=store.publish,
        discard=store.discard,
    )
    state = State(
        settings=settings,
        data_dir=data_dir,
        registry=registry,
        auth=Auth(settings.api_keys, registry),
        store=store,
        renders=renders,
        jobs=jobs,
        uploads=Uploads(data_dir, settings.upload_limit),
        metrics=metrics,
        rate=RateLimiter(settings.request_rate, burst=2 * settings.request_rate),
    )
    metrics.attach(store.cache, registry.job_counts, lambda: state.viewers)
    from vastray.server.stream import StreamHub

    state.streams = StreamHub(state)
    return state


def create_app(settings: Settings | None = None) -> FastAPI:
    settings = settings or Settings()

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        state: State = app.state.vastray
        state.jobs.start(asyncio.get_running_loop())
        state.streams.scheduler.start()
        if settings.demo and state.registry.get_meta("demo_submitted") is None:
            from vastray.server.routes.jobs import submit_build

            state.registry.set_meta("demo_submitted", str(time.time()))
            if not state.registry.models():
                job = submit_build(state, source="demo", name="demo", options=None)
                log.info("first start: building the demo model (job %s); the API is usable meanwhile", job.id)
        yield
        state.stopping.set()
        await state.streams.close_all("the server is shutting down")
        await state.streams.scheduler.stop()
        state.renders.shutdown()
        await asyncio.to_thread(state.jobs.shutdown)
        state.store.close()
        state.registry.close()

    app = FastAPI(
        title="vastray",
        version=__version__,
        description="Render service for massive 3D models: out-of-core CPU ray tracing with level of detail. "
        "Write endpoints need an API key; renders need the key or a viewing token.",
        lifespan=lifespan,
    )
    app.state.vastray = build_state(settings)
    errors.install(app)
    if settings.cors_origins:
        app.add_middleware(
            CORSMiddleware,
            allow_origins=settings.cors_origins,
            allow_methods=["*"],
            allow_headers=["*"],
            expose_headers=["X-Vastray-Frames", "X-Vastray-Render-Ms", "X-Vastray-Complete"],
        )
    app.add_middleware(BodyLimit, limit=settings.max_message_bytes, exempt=("/api/uploads",))

    from vastray.server import stream
    from vastray.server.routes import health, jobs, model_views, models, render, reviews

    for module in (health, models, model_views, jobs, render, reviews, stream):
        app.include_router(module.router)
    # The viewer page's scripts and styles (the page itself is "/").
    app.mount("/ui", StaticFiles(directory=health.WEB), name="ui")
    return app
