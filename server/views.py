"""A view: what one stream shows (a model, a camera, a viewport, quality settings) and
the state machine that decides what to render next for it.

    moving    a camera arrived since the last frame: render it now at the scale and
              accuracy the controller picks to hold the target frame rate
    refining  the camera has been still for SETTLE seconds: pass 1 at full scale and the
              chosen accuracy (repeated as blocks arrive until nothing is missing), then
              jittered passes averaged into it (anti-aliasing)
    idle      the last pass was sent with the final flag: nothing to do, no CPU spent,
              until the camera, the viewport or the quality changes

A view renders for its subscribers (the connections that show it: one viewer, or a
presenter and the followers of a review) and only when one of them can take a frame;
every subscriber gets the same encoded bytes.
"""

from __future__ import annotations

import copy
import time
from dataclasses import dataclass, replace
from typing import Any, Protocol

import numpy as np

from vastray import native
from vastray.camera import Camera, Vec3
from vastray.outofcore import OutOfCoreModel
from vastray.parts import PartTable
from vastray.protocol import (
    FLAG_COMPLETE,
    FLAG_FINAL,
    FLAG_MOVING,
    CameraState,
    SectionPlane,
    StreamQuality,
    Viewport,
)
from vastray.renderer import Frame
from vastray.schemas import native_sections
from vastray.server.controller import QualityController
from vastray.server.encoders import encode

SETTLE_SECONDS = 0.12  # a camera still this long starts refinement
MAX_STALLS = 3  # incomplete passes without any block arriving before the view gives up waiting


class Subscriber(Protocol):
    def can_take(self) -> bool: ...

    def offer(self, frame: RenderedFrame) -> None: ...


@dataclass
class RenderJob:
    version: int  # the view's state version it renders
    camera: Camera  # resolved, at the job's image size
    seq: int
    camera_at: float  # when that camera arrived (monotonic)
    params: native.RenderParams
    scale: float
    moving: bool
    pass_number: int
    jitter: tuple[float, float]
    jpeg_quality: int
    accumulate: bool  # average into the view's refinement image
    budget_seconds: float = 0.0
    # The sum of the earlier passes' images and their count (None/0 for pass 1), taken
    # when the job was made: rendering never reads the view's changing state.
    accum: np.ndarray | None = None
    accum_n: int = 0
    camera_state: CameraState | None = None  # the camera as the client gave it (no jitter)


@dataclass
class RenderedFrame:
    job: RenderJob
    data: bytes  # the encoded image
    format: str
    width: int
    height: int
    flags: int
    stats: native.FrameStats
    render_ms: float
    encode_ms: float
    started_at: float  # monotonic
    finished_at: float
    image: np.ndarray | None = None  # the displayed pixels of a refinement pass (the average so far)
    raw: np.ndarray | None = None  # this pass's own pixels


def halton(index: int, base: int) -> float:
    f, r = 1.0, 0.0
    while index > 0:
        f /= base
        r += f * (index % base)
        index //= base
    return r


def jittered(camera: Camera, dx: float, dy: float) -> Camera:
    """The camera with its image moved by (dx, dy) pixels: the target shifts in the
    image plane (an orthographic camera's eye with it). (A perspective image plane also
    tilts by about a pixel's angle, an error of the order of a pixel squared: invisible.)"""
    if dx == 0.0 and dy == 0.0:
        return camera
    eye = np.asarray(camera.eye)
    _, right, up = camera.basis()
    dist = float(np.linalg.norm(np.asarray(camera.target) - eye))
    shift = (right * (2.0 * dx / camera.width) - up * (2.0 * dy / camera.height)) * dist
    target = np.asarray(camera.target) + shift
    eye = eye + shift if camera.orthographic else eye  # parallel rays move, not turn
    return replace(
        camera,
        eye=(float(eye[0]), float(eye[1]), float(eye[2])),
        target=(float(target[0]), float(target[1]), float(target[2])),
    )


def camera_of(state: CameraState, width: int, height: int) -> Camera:
    """The renderers' camera of a client's camera state, at an image size."""
    return Camera(state.eye, state.target, state.up, state.fov, width, height, state.projection)


class View:
    def __init__(
        self,
        view_id: str,
        model_id: str,
        model: OutOfCoreModel,
        camera: CameraState,
        viewport: Viewport,
        quality: StreamQuality,
        *,
        render_threads: int,
        parts: PartTable | None = None,
    ) -> None:
        self.id = view_id
        self.model_id = model_id
        self.model = model
        self.camera = camera
        self.viewport = viewport
        self.quality = quality
        self.render_threads = render_threads
        self.camera_at = time.monotonic()
        self.version = 1  # bumps on every change of camera, viewport or quality
        self.moving_since_version = 1  # the camera moved at this version (and not since)
        self.rendered_version = 0
        self.phase = "moving"
        self.refine_pass = 0  # the last refinement pass done (0: none)
        self.accum: np.ndarray | None = None
        self.accum_n = 0
        self.waiting_for_data = False
        self.data_epoch = 0  # the scheduler's block-arrival count when the last frame began
        self.stalls = 0
        self.controller = QualityController()
        self.max_gain = 1.0  # the scheduler's frames in flight for the moving views
        self.last_moving_finish: float | None = None
        self.sections: list[SectionPlane] = []
        self.highlight: list[int] = []
        self.parts = parts if parts is not None else PartTable.empty()
        self._highlight_runs: tuple[tuple[int, ...], np.ndarray] | None = None
        self.subscribers: set[Subscriber] = set()
        self.busy = False
        self.vtime = 0.0
        self.last_final: RenderedFrame | None = None
        self.frames_rendered = 0
        self.render_seconds = 0.0
        self.stall_reported = False

    # -- changes from clients --------------------------------------------------------------

    def set_camera(self, camera: CameraState) -> None:
        self.camera = camera
        self.camera_at = time.monotonic()
        self.version += 1
        self.moving_since_version = self.version
        self._restart("moving")

    def set_viewport(self, viewport: Viewport) -> None:
        self.viewport = viewport
        self.version += 1
        self._restart("refining")

    def set_quality(self, quality: StreamQuality) -> None:
        self.quality = quality
        self.version += 1
        self._restart("refining")

    def set_sections(self, planes: list[SectionPlane]) -> None:
        self.sections = planes
        self.version += 1
        self._restart("moving")  # planes are dragged: answer at the moving rate

    def set_highlight(self, parts: list[int]) -> None:
        self.highlight = parts
        self.version += 1
        self._restart("refining")

    def highlight_runs(self) -> np.ndarray:
        """The highlighted parts as the renderer takes them (runs of triangle ids),
        worked out once per highlight set, not per frame."""
        key = tuple(self.highlight)
        if self._highlight_runs is None or self._highlight_runs[0] != key:
            self._highlight_runs = (key, self.parts.ranges(key))
        return self._highlight_runs[1]

    def state(self) -> dict[str, Any]:
        """What a saved view keeps."""
        return {
            "camera": self.camera.model_dump(),
            "quality": self.quality.model_dump(),
            "sections": [p.model_dump() for p in self.sections],
            "highlight": list(self.highlight),
        }

    def apply(self, state: dict[str, Any]) -> None:
        """Goes to a saved view."""
        camera = CameraState(**{**state["camera"], "seq": self.camera.seq + 1})
        self.quality = StreamQuality(**state.get("quality", self.quality.model_dump()))
        self.sections = [SectionPlane(**p) for p in state.get("sections", [])]
        self.highlight = list(state.get("highlight", []))
        self.set_camera(camera)

    def _restart(self, phase: str) -> None:
        self.phase = phase
        self.refine_pass = 0
        self.accum = None
        self.accum_n = 0
        self.waiting_for_data = False
        self.stalls = 0
        self.stall_reported = False

    # -- scheduling ------------------------------------------------------------------------

    def wants_frame(self) -> bool:
        return any(s.can_take() for s in self.subscribers)

    def next_job(self, now: float, data_epoch: int, budget_seconds: float) -> RenderJob | float | None:
        """The next frame to render, or the seconds to wait before there is one (a
        settling camera), or None (idle, or waiting for data that has not arrived)."""
        if self.busy or self.phase == "idle":
            return None
        if self.phase == "moving" and self.rendered_version < self.version:
            return self._job(moving=True, budget_seconds=budget_seconds)
        if self.phase == "moving":
            wait = self.camera_at + SETTLE_SECONDS - now
            if wait > 0:
                return wait
            self.phase = "refining"
        if self.waiting_for_data and data_epoch == self.data_epoch:
            return None  # the last pass lacked blocks; render it again when some arrive
        return self._job(moving=False, budget_seconds=budget_seconds)

    def _job(self, *, moving: bool, budget_seconds: float) -> RenderJob:
        q = self.quality
        full_w, full_h = self.viewport.width, self.viewport.height
        if moving:
            scale, poe = self.controller.moving_settings(q.pixels_of_error, q.min_scale, q.max_moving_poe)
            pass_number, jitter, accumulate = 0, (0.0, 0.0), False
        else:
            scale, poe = 1.0, q.pixels_of_error
            pass_number = self.refine_pass + (0 if self.waiting_for_data else 1)
            pass_number = max(1, pass_number)
            k = pass_number - 1
            jitter = (halton(k, 2) - 0.5, halton(k, 3) - 0.5) if k > 0 else (0.0, 0.0)
            accumulate = True
        width, height = max(1, round(full_w * scale)), max(1, round(full_h * scale))
        c = self.camera
        camera = jittered(camera_of(c, width, height), *jitter)
        params = q.to_native(threads=self.render_threads)
        params.pixels_of_error = poe
        params.sections = native_sections(self.sections)
        params.highlight = self.highlight_runs()
        # Each refinement pass draws new AO and diffuse directions, so the average of the
        # passes has their samples together, not the same noise again.
        params.sample_index = max(0, pass_number - 1)
        base, n = (self.accum, self.accum_n) if accumulate and pass_number > 1 else (None, 0)
        return RenderJob(
            self.version,
            camera,
            c.seq,
            self.camera_at,
            params,
            scale if moving else 1.0,
            moving,
            pass_number,
            jitter,
            q.jpeg_quality,
            accumulate,
            budget_seconds,
            base,
            n,
            c,
        )

    # -- rendering (on the render executor) --------------------------------------------------

    def render(self, job: RenderJob) -> RenderedFrame:
        started = time.monotonic()
        frame: Frame = self.model.render(job.camera, job.params)
        image = frame.image
        if job.accum is not None and frame.complete:
            image = ((job.accum + image) / (job.accum_n + 1)).round().astype(np.uint8)
        t = time.monotonic()
        data = encode(image, "jpeg", quality=job.jpeg_quality)
        finished = time.monotonic()
        flags = (FLAG_COMPLETE if frame.complete else 0) | (FLAG_MOVING if job.moving else 0)
        return RenderedFrame(
            job,
            data,
            "jpeg",
            job.camera.width,
            job.camera.height,
            flags,
            frame.stats,
            frame.stats.milliseconds,
            1000 * (finished - t),
            started,
            finished,
            image if job.accumulate else None,
            frame.image if job.accumulate else None,
        )

    # -- results (back on the event loop) --------------------------------------------------

    def finish(
        self, job: RenderJob, result: RenderedFrame, data_epoch: int
    ) -> tuple[RenderedFrame | None, str | None]:
        """Takes a rendered frame into the view's state. Returns the frame to send (None
        if the view changed meanwhile, so it is stale) and a warning for the clients."""
        self.busy = False
        self.frames_rendered += 1
        seconds = result.finished_at - result.started_at
        self.render_seconds += seconds
        q = self.quality
        if job.moving:
            # Sent even if the camera moved on meanwhile: it is the newest picture there
            # is, and a camera that keeps moving would otherwise never get one.
            self.controller.observe(
                seconds, job.budget_seconds, q.min_scale, q.max_moving_poe, q.pixels_of_error
            )
            if self.last_moving_finish is not None:
                self.controller.observe_rate(
                    result.finished_at - self.last_moving_finish, q.target_fps, self.max_gain
                )
            self.last_moving_finish = result.finished_at
            if job.version == self.version:
                self.rendered_version = job.version
            return result, None
        self.last_moving_finish = None  # the next moving frame starts a new run of them
        if job.version != self.version:
            return None, None  # a refinement of a view that has changed: a new frame follows
        self.rendered_version = job.version
        warning = None
        stats = result.stats
        self.data_epoch = data_epoch
        if not stats.complete:
            if stats.pending > 0:
                self.waiting_for_data = True
                self.stalls = 0
                return result, None
            # Incomplete with nothing pending: damaged blocks, or a cache too small for the
            # view. Try again a few times (a block may have arrived meanwhile), then give up.
            self.stalls += 1
            if self.stalls < MAX_STALLS:
                return result, None
            if not self.stall_reported:
                self.stall_reported = True
                warning = (
                    "the view cannot be completed: the block cache is too small for it or blocks are "
                    "damaged; showing what is loaded"
                )
        self.waiting_for_data = False
        self.refine_pass = job.pass_number
        if result.raw is not None:
            if job.pass_number == 1 or self.accum is None:
                self.accum = result.raw.astype(np.float32)
                self.accum_n = 1
            else:
                self.accum = self.accum + result.raw
                self.accum_n += 1
        passes = q.aa_passes if q.refine else 1
        if self.refine_pass >= passes:
            self.phase = "idle"
            result.flags |= FLAG_FINAL
            self.last_final = result
        return result, warning

    def measure_accuracy(self, timeout: float = 120.0) -> dict[str, Any]:
        """What the chosen accuracy costs on this very view (on the render executor):
        the view at its pixels of error and at full detail, each complete, compared
        pixel by pixel — the share of pixels whose hit differs (another triangle, a voxel
        instead of a triangle, or a miss) and the PSNR of the image — with each frame's
        render time. Single passes on both sides, so anti-aliasing plays no part."""
        c, vp = self.camera, self.viewport
        camera = camera_of(c, vp.width, vp.height)
        chosen = self.quality.to_native(threads=self.render_threads)
        chosen.sections = native_sections(self.sections)
        chosen.highlight = self.highlight_runs()
        exact = copy.copy(chosen)
        exact.pixels_of_error = 0.0
        shown = self.model.render_complete(camera, chosen, timeout=timeout)
        full = self.model.render_complete(camera, exact, timeout=timeout)
        differs = float((shown.prim != full.prim).mean())
        mse = float(((shown.image.astype(np.float64) - full.image.astype(np.float64)) ** 2).mean())
        return {
            "type": "accuracy",
            "camera_seq": c.seq,
            "pixels_of_error": chosen.pixels_of_error,
            "hit_differs": differs,
            "psnr_db": None if mse == 0 else 10 * np.log10(255.0**2 / mse),
            "frame_ms": shown.stats.milliseconds,
            "full_detail_ms": full.stats.milliseconds,
            "complete": bool(shown.complete and full.complete),
            "width": vp.width,
            "height": vp.height,
        }

    def describe(self) -> dict[str, Any]:
        return {
            "id": self.id,
            "model": self.model_id,
            "phase": self.phase,
            "pass": self.refine_pass,
            "subscribers": len(self.subscribers),
            "frames": self.frames_rendered,
        }


def camera_problem(camera: CameraState) -> str | None:
    """Why no frame can be rendered from this camera (eye on the target, up along the
    view, ...), or None. Pydantic checks each field; this checks them together."""
    try:
        camera_of(camera, 16, 16).validate()
    except ValueError as exc:
        return f"camera: {exc}"
    return None


def default_camera(model: OutOfCoreModel, viewport: Viewport, up: Vec3 | None = None) -> CameraState:
    """The whole model from a three-quarter view, turned about its `up`."""
    from vastray.camera import Y_UP, frame_bounds

    lo, hi = model.bounds
    c = frame_bounds(lo, hi, width=viewport.width, height=viewport.height, up=up or Y_UP)
    return CameraState(seq=0, eye=c.eye, target=c.target, up=c.up, fov=c.fov)
