"""Rendering for the server: one-shot images and pick queries now, streamed frames
through the scheduler (scheduler.py) next. Everything goes through the `Renderer`
interface of the models in the shared cache (vastray/renderer.py), and every render and
encode runs on the render executor, never on the event loop."""

from __future__ import annotations

import asyncio
import math
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any, TypeVar

import numpy as np

from vastray.camera import Y_UP, Camera, Vec3, resolve_camera
from vastray.outofcore import CacheTooSmallError, OutOfCoreModel, RenderCancelledError
from vastray.parts import PartTable
from vastray.renderer import Frame, Renderer
from vastray.schemas import (
    CameraSpec,
    PickHit,
    PickRequest,
    PickResponse,
    RenderRequest,
    SectionPlane,
    native_sections,
)
from vastray.server.encoders import MEDIA_TYPES, encode
from vastray.server.errors import ApiError
from vastray.server.metrics import Metrics
from vastray.server.model_store import ModelStore

T = TypeVar("T")


@dataclass
class RenderedImage:
    data: bytes
    media_type: str
    frame: Frame
    encode_ms: float


def camera_for(spec: CameraSpec, renderer: Renderer, max_pixels: int, model_up: Vec3 | None) -> Camera:
    """The camera a request describes, checked before any work: the pixel budget, then
    the native checks (finite values, eye != target, up not along the view, fov). A
    spec without an up takes the model's."""
    if spec.pixels > max_pixels:
        side = int(math.sqrt(max_pixels))
        raise ApiError(
            422,
            "image_too_large",
            f"a {spec.width}x{spec.height} image is {spec.pixels:,} pixels; the server's pixel budget "
            f"is {max_pixels:,} (about {side}x{side})",
        )
    lo, hi = renderer.bounds
    try:
        camera = resolve_camera(
            lo,
            hi,
            eye=spec.eye,
            target=spec.target,
            up=spec.up or model_up or Y_UP,
            view=spec.view,
            fov=spec.fov,
            width=spec.width,
            height=spec.height,
            projection=spec.projection,
        )
        camera.validate()
    except ValueError as exc:
        raise ApiError(422, "invalid_camera", f"camera: {exc}") from None
    return camera


class RenderService:
    def __init__(
        self,
        store: ModelStore,
        *,
        workers: int,
        threads: int,
        max_pixels: int,
        max_timeout: float,
        metrics: Metrics,
    ) -> None:
        self.store = store
        self.threads = threads
        self.max_pixels = max_pixels
        self.max_timeout = max_timeout
        self.metrics = metrics
        self.executor = ThreadPoolExecutor(max_workers=workers, thread_name_prefix="vastray-render")
        self.stopping = threading.Event()

    async def run(self, fn: Any, *args: Any) -> Any:
        return await asyncio.get_running_loop().run_in_executor(self.executor, fn, *args)

    async def render_image(self, model_id: str, request: RenderRequest) -> RenderedImage:
        if request.timeout > self.max_timeout:
            raise ApiError(
                422,
                "invalid_request",
                f"timeout {request.timeout:g} s is longer than this server allows ({self.max_timeout:g} s)",
            )
        params = request.quality.to_native(threads=self.threads)
        params.sections = native_sections(request.sections)
        return await self.run(self._render_image, model_id, request, params)

    def _render_image(self, model_id: str, request: RenderRequest, params: Any) -> RenderedImage:
        with self.store.lease(model_id) as model:
            camera = camera_for(request.camera, model, self.max_pixels, self.store.row(model_id).up)
            frame = self._complete(model, camera, params, request.timeout)
            start = time.perf_counter()
            data = encode(frame.image, request.format, quality=request.jpeg_quality)
            encode_ms = 1000 * (time.perf_counter() - start)
        self.metrics.frame_rendered("oneshot", frame.stats, encode_ms / 1000)
        self.metrics.frames_sent.labels("oneshot").inc()
        self.metrics.bytes_sent.labels("oneshot").inc(len(data))
        return RenderedImage(data, MEDIA_TYPES[request.format], frame, encode_ms)

    def _complete(self, model: OutOfCoreModel, camera: Camera, params: Any, timeout: float) -> Frame:
        try:
            return model.render_complete(camera, params, timeout=timeout, cancelled=self.stopping.is_set)
        except TimeoutError:
            raise ApiError(
                504,
                "render_timeout",
                f"the view was not complete after {timeout:g} s (its data is still loading); "
                "ask again, allow a longer timeout, or raise pixels_of_error",
            ) from None
        except CacheTooSmallError as exc:
            raise ApiError(507, "cache_too_small", str(exc)) from None
        except RenderCancelledError:
            raise ApiError(503, "shutting_down", "the server is shutting down") from None
        except ValueError as exc:
            raise ApiError(422, "invalid_quality", str(exc)) from None

    async def pick(self, model_id: str, request: PickRequest) -> PickResponse:
        return await self.run(self._pick, model_id, request)

    def _pick(self, model_id: str, request: PickRequest) -> PickResponse:
        with self.store.lease(model_id) as model:
            origins, directions = [], []
            if request.points:
                assert request.camera is not None
                camera = camera_for(request.camera, model, self.max_pixels, self.store.row(model_id).up)
                o, d = camera.image_rays(np.asarray(request.points, dtype=np.float64), model.bounds)
                origins.append(o)
                directions.append(d)
            if request.rays:
                rays = np.asarray(request.rays, dtype=np.float64)
                origins.append(rays[:, 0])
                directions.append(rays[:, 1])
            return self.pick_rays(
                model,
                np.concatenate(origins),
                np.concatenate(directions),
                request.timeout,
                request.sections,
                parts=model.part_table,
            )

    def pick_rays(
        self,
        model: OutOfCoreModel,
        origins: np.ndarray,
        directions: np.ndarray,
        timeout: float,
        sections: list[SectionPlane] | None = None,
        *,
        parts: PartTable | None = None,
    ) -> PickResponse:
        """Full-detail hits of world rays, as the wire has them (on the render executor)."""
        start = time.perf_counter()
        hits = model.pick(origins, directions, timeout=timeout, sections=native_sections(sections or []))
        part_of = parts.part_of(hits.prim) if parts is not None else np.full(len(hits.t), -1)
        out = []
        for i in range(len(hits.t)):
            found = bool(hits.prim[i] >= 0)
            part = int(part_of[i])
            out.append(
                PickHit(
                    hit=found,
                    complete=bool(hits.complete[i]),
                    distance=float(hits.t[i]) if found else None,
                    position=tuple(float(x) for x in hits.position[i]) if found else None,  # type: ignore[arg-type]
                    normal=tuple(float(x) for x in hits.normal[i]) if found else None,  # type: ignore[arg-type]
                    triangle=int(hits.prim[i]) if found else None,
                    part_id=part if part >= 0 else None,
                    part=parts.name(part) if parts is not None and part >= 0 else None,
                )
            )
        elapsed = time.perf_counter() - start
        self.metrics.pick_seconds.observe(elapsed)
        return PickResponse(hits=out, milliseconds=1000 * elapsed)

    def shutdown(self) -> None:
        self.stopping.set()
        self.executor.shutdown(wait=True, cancel_futures=True)
