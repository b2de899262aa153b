"""Rendering built models out of core: the block cache and the models opened in it.

A built model (docs/FORMAT.md) is never loaded whole. `OutOfCoreModel` opens it in a
`native.BlockCache`: a byte budget of 64 KB slots shared by every model of the process,
filled by fetcher threads. Frames are traced from whatever blocks are cached, with level
of detail (paper 000): a ray stops at a voxel once the voxel looks no bigger than the
chosen pixels of error (PoE), and where data is still missing it hits the last voxel it
passed and asks for the block. So `render` never waits: the first frame of a model of
any size is ready at once, and later frames refine as blocks arrive. `render_complete`
is the full-detail (or fixed-accuracy) mode: it renders until nothing is missing.
"""

from __future__ import annotations

import os
import threading
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from vastray import native
from vastray.camera import Camera
from vastray.modelfile import ModelError, ModelFile, ModelPart
from vastray.parts import PartTable
from vastray.renderer import Frame, RayHits, Sections, render_params, trace
from vastray.units import parse_bytes

DEFAULT_CACHE_BUDGET = 1 << 30
DEFAULT_FETCHERS = 2
PRIORITIES = ("count", "size")  # paper 000 §5.3 request counts, paper 003 projected size
# Node levels loaded when a model opens: a handful of blocks that give the first frame
# voxels a few levels down instead of the single root voxel.
OPEN_PRELOAD_LEVELS = 3
# Blocks a render_complete frame may queue (the cache caps it at its max_pending): a
# full-detail render waits for its data, so it asks for all it finds missing at once.
FULL_DETAIL_REQUEST_LIMIT = 4096
# render_complete first finds the view's blocks with frames of 1/DISCOVERY_SCALE the
# width and height whose rays have the full frame's LOD cone (pixels of error scaled by
# the pixel size): each frame finds what is missing one tree level deeper, so a cold view
# takes about a frame per level, and these frames cost a sixteenth of a full one. Full
# frames then pick up what only their finer rays reach. Images smaller than
# DISCOVERY_MIN_SIDE on a side skip it.
DISCOVERY_SCALE = 4
DISCOVERY_MIN_SIDE = 64


class CacheTooSmallError(RuntimeError):
    """A complete image of this view needs more blocks than the cache can hold at once."""


class RenderCancelledError(RuntimeError):
    """render_complete was told to stop (its `cancelled` callback said so)."""


_shared_lock = threading.Lock()
_shared: native.BlockCache | None = None


def make_cache(
    budget: int = DEFAULT_CACHE_BUDGET, fetchers: int = DEFAULT_FETCHERS, priority: str = "count"
) -> native.BlockCache:
    """A new block cache. `budget` is in bytes (at least 256 KiB)."""
    if priority not in PRIORITIES:
        raise ValueError(f"priority must be one of {', '.join(PRIORITIES)}")
    return native.BlockCache(int(budget), int(fetchers), priority)


def shared_cache() -> native.BlockCache:
    """The process-wide cache, created on first use from VASTRAY_CACHE (a size such as
    512M; default 1G) and VASTRAY_FETCHERS (default 2)."""
    global _shared
    with _shared_lock:
        if _shared is None:
            budget = parse_bytes(os.environ.get("VASTRAY_CACHE", "1G"), "VASTRAY_CACHE")
            fetchers = int(os.environ.get("VASTRAY_FETCHERS", DEFAULT_FETCHERS))
            _shared = make_cache(budget, fetchers)
        return _shared


def discovery_pass(
    camera: native.Camera, params: native.RenderParams
) -> tuple[native.Camera, native.RenderParams]:
    """A camera of 1/DISCOVERY_SCALE the image sides, and params whose LOD cones equal
    those of `camera`'s rays: the cone is pixels_of_error x the pixel angle (2 tan(fov/2)
    / height), so the pixels of error shrink with the height (an explicit solid angle is
    absolute and stays)."""
    width = max(1, -(-camera.width // DISCOVERY_SCALE))
    height = max(1, -(-camera.height // DISCOVERY_SCALE))
    coarse = native.Camera(
        camera.eye, camera.target, camera.up, camera.fov, width, height, camera.orthographic
    )
    poe = params.pixels_of_error * height / camera.height
    return coarse, render_params(params, pixels_of_error=poe)


class OutOfCoreModel:
    """A built model opened in a block cache. Opening reads the header and index and
    loads the coarsest levels; everything else arrives while frames are rendered."""

    def __init__(
        self,
        path: str | os.PathLike[str],
        cache: native.BlockCache | None = None,
        *,
        preload_levels: int = OPEN_PRELOAD_LEVELS,
    ) -> None:
        self.path = str(path)
        self.cache = cache if cache is not None else shared_cache()
        start = time.perf_counter()
        try:
            self._model = self.cache.open(self.path)
        except (ValueError, RuntimeError) as e:
            # The native reader names the file and the problem; keep one error type.
            raise ModelError(str(e)) from None
        if preload_levels > 1:
            self._model.preload_levels(preload_levels)
        self.open_seconds = time.perf_counter() - start
        self._part_table: PartTable | None = None
        self._part_lock = threading.Lock()

    @property
    def part_table(self) -> PartTable:
        """The part table and runs, read once through ModelFile on first use (the native
        reader has already checked the section's checksum on open)."""
        with self._part_lock:
            if self._part_table is None:
                with ModelFile(self.path) as f:
                    self._part_table = PartTable.of_file(f)
            return self._part_table

    @property
    def parts(self) -> list[ModelPart]:
        """The model's parts (empty when its input had none); see ModelFile.parts."""
        return list(self.part_table.parts)

    def part_of(self, triangle_ids: np.ndarray) -> np.ndarray:
        """The part (int32, -1 for none) of each input triangle id; see ModelFile.part_of."""
        return self.part_table.part_of(triangle_ids)

    @property
    def name(self) -> str:
        return os.path.basename(self.path)

    @property
    def up(self) -> tuple[float, float, float] | None:
        """Which way is up in the model, as its builder was told (ModelFile.up), or None."""
        with ModelFile(self.path) as f:
            return f.up

    @property
    def bounds(self) -> tuple[list[float], list[float]]:
        return self._model.bounds

    @property
    def triangle_count(self) -> int:
        return int(self._model.triangle_count)

    @property
    def block_count(self) -> int:
        return int(self._model.block_count)

    @property
    def file_size(self) -> int:
        return int(self._model.file_size)

    @property
    def errors(self) -> list[str]:
        """Blocks that failed to read or verify; they render as their parent voxels."""
        return list(self._model.errors)

    def render(self, camera: Camera, params: native.RenderParams | None = None, **fields: Any) -> Frame:
        """One frame from what is cached now; never waits for data (frame.complete says
        whether anything was missing)."""
        return trace(self._model, camera, params, **fields)

    def render_complete(
        self,
        camera: Camera,
        params: native.RenderParams | None = None,
        *,
        timeout: float = 600.0,
        cancelled: Callable[[], bool] | None = None,
        **fields: Any,
    ) -> Frame:
        """Renders until nothing is missing for this view at this accuracy
        (pixels_of_error 0: full detail). `frames` and `seconds` of the result count
        the whole wait. `cancelled` is polled between frames (a server's time limit or
        a client that went away)."""
        params = render_params(params, **fields)
        if params.request_limit == 0:
            # It waits for the data anyway: let each frame queue all it found missing
            # (up to the cache's queue), not the interactive per-frame bound.
            params = render_params(params, request_limit=FULL_DETAIL_REQUEST_LIMIT)
        native_camera = camera.to_native() if isinstance(camera, Camera) else camera
        start = time.perf_counter()
        frames = 0
        stalled = 0
        passes = [(native_camera, params)]
        if min(native_camera.width, native_camera.height) >= DISCOVERY_MIN_SIDE:
            passes.insert(0, discovery_pass(native_camera, params))
        while True:
            pass_camera, pass_params = passes[0]
            frame = trace(self._model, pass_camera, pass_params)
            frames += 1
            stats = frame.stats
            if stats.complete or (stats.bad_blocks and stats.pending == 0):
                if len(passes) == 1:
                    break
                passes.pop(0)  # the coarse frames found all they can: on to full frames
                continue
            if cancelled is not None and cancelled():
                raise RenderCancelledError(f"{self.name}: render cancelled")
            if time.perf_counter() - start > timeout:
                raise TimeoutError(f"{self.name}: view not complete after {timeout:g} s")
            # Between frames, let the fetchers work through what this frame asked for
            # (another frame now would only find the same blocks missing, and take the
            # cores the fetchers decompress on), but no longer than a few frame times,
            # so blocks found one level deeper join the queue early. A cache that cannot
            # make room (the view's working set is larger than the budget) makes no
            # progress. A cache with free slots that makes none is waiting for a slow disk
            # (seen here: three frames without a finished fetch while a cold 4 GiB model
            # needed 548 MiB of a 5 GiB cache), which the timeout bounds.
            progressed = self._wait_for_queue(max(0.05, 3 * stats.milliseconds / 1000.0), start + timeout)
            stalled = 0 if progressed or stats.blocks_loaded else stalled + 1
            if stalled >= 3 and (totals := self.cache.totals())["free_slots"] == 0:
                raise CacheTooSmallError(
                    f"{self.name}: this view needs more blocks than the cache holds "
                    f"({totals['slot_count']} slots of 64 KiB, {stats.working_set_blocks} in use); "
                    "raise the cache budget or the pixels of error"
                )
        frame.frames = frames
        frame.seconds = time.perf_counter() - start
        return frame

    def _wait_for_queue(self, seconds: float, deadline: float) -> bool:
        """Waits until the fetch queue is empty, `seconds` pass or `deadline` comes;
        True if some fetch finished meanwhile."""

        def fetched() -> tuple[int, int, int]:
            t = self.cache.totals()
            return t["bytes_read"], t["failed"], t["ready"]

        before = fetched()
        wait = max(0.001, min(seconds, deadline - time.perf_counter()))
        self.cache.wait_idle(1000.0 * wait)
        after = fetched()
        return after[:2] != before[:2] or after[2] > 0

    def pick(
        self, origins: np.ndarray, directions: np.ndarray, *, timeout: float = 10.0, sections: Sections = ()
    ) -> RayHits:
        """Full-detail closest hits of world rays. Rays whose blocks are not cached are
        asked again as the fetchers bring them, until all are answered or `timeout`
        seconds pass (those left have complete False). With section planes a ray sees
        only the kept side, and the cap where it enters a cut solid."""
        o = np.ascontiguousarray(origins, dtype=np.float64).reshape(-1, 3)
        d = np.ascontiguousarray(directions, dtype=np.float64).reshape(-1, 3)
        planes = list(sections)
        deadline = time.perf_counter() + timeout
        out = self._model.intersect(o, d, sections=planes)
        hits = RayHits(out["t"], out["position"], out["normal"], out["prim"], out["complete"])
        while not hits.complete.all() and time.perf_counter() < deadline:
            self.cache.wait_for_fetches(max(1.0, 1000.0 * min(0.25, deadline - time.perf_counter())))
            todo = np.flatnonzero(~hits.complete)
            again = self._model.intersect(o[todo], d[todo], sections=planes)
            for name in ("t", "position", "normal", "prim", "complete"):
                getattr(hits, name)[todo] = again[name]
        return hits

    def close(self) -> None:
        self._model.close()

    def __enter__(self) -> OutOfCoreModel:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
