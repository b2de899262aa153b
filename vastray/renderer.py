"""One way to render, whatever is rendered.

A `Renderer` takes a camera and render parameters and gives a `Frame`; it also answers
full-detail ray queries (`pick`). Two implementations share it:

- `vastray.outofcore.OutOfCoreModel`: a built model through the shared block cache,
  with level of detail; `render` never waits for data, `render_complete` waits until
  nothing the view needs is missing.
- `vastray.render.SceneRenderer`: an in-core scene (a mesh, a procedural scene, or a
  built model decoded whole), always complete and at full detail.

Parameters and statistics are the native structs (`native.RenderParams`,
`native.FrameStats`), bound once: the CLI, the server's wire schemas and the Python
client use the same names and the same defaults.
"""

from __future__ import annotations

import copy
import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, Protocol, runtime_checkable

import numpy as np

from vastray import native
from vastray.camera import Camera

SHADING_MODES: tuple[str, ...] = tuple(native.SHADING_MODES)
# The modes that trace any-hit (shadow, AO) rays: in core they walk the scene's 8-wide BVH.
ANY_HIT_SHADINGS: tuple[str, ...] = tuple(native.ANY_HIT_SHADINGS)
PRIM_BACKGROUND = -1  # Frame.prim where a pixel sees nothing
PRIM_VOXEL = -2  # Frame.prim where a pixel shows a LOD voxel instead of a triangle

# The fields of native.RenderParams, in a stable order, for schemas and error messages.
RENDER_PARAM_FIELDS: tuple[str, ...] = (
    "shading",
    "ao_samples",
    "ao_distance",
    "sun_direction",
    "threads",
    "tile_size",
    "packets",
    "pixels_of_error",
    "solid_angle",
    "sample_index",
    "request_limit",
    "sections",
    "highlight",
)

# Section planes: (nx, ny, nz, offset) each; geometry where n . p + offset < 0 is cut away.
Sections = Sequence[tuple[float, float, float, float]]


def render_params(base: native.RenderParams | None = None, **fields: Any) -> native.RenderParams:
    """A validated copy of `base` (default: the defaults) with `fields` changed. Unknown
    names are a TypeError; values outside their range a ValueError naming the field."""
    params = copy.copy(base) if base is not None else native.RenderParams()
    for name, value in fields.items():
        if name not in RENDER_PARAM_FIELDS:
            raise TypeError(f"unknown render parameter {name!r}; known: {', '.join(RENDER_PARAM_FIELDS)}")
        setattr(params, name, value)
    params.validate()
    return params


def params_dict(params: native.RenderParams) -> dict[str, Any]:
    return {name: getattr(params, name) for name in RENDER_PARAM_FIELDS}


@dataclass
class Frame:
    image: np.ndarray  # (H, W, 3) uint8
    depth: np.ndarray  # (H, W) float32: distance along the unit view ray, inf where nothing was hit
    prim: np.ndarray  # (H, W) int32: input triangle id, PRIM_BACKGROUND, or PRIM_VOXEL
    stats: native.FrameStats
    frames: int = 1  # frames rendered to get this one (render_complete renders several)
    seconds: float = 0.0  # wall time of all of them, waits for data included

    @property
    def complete(self) -> bool:
        """Nothing this view needs at this accuracy was missing."""
        return bool(self.stats.complete)


def trace(
    target: native.Scene | native.CachedModel,
    camera: Camera | native.Camera,
    params: native.RenderParams | None = None,
    **fields: Any,
) -> Frame:
    """One frame of a native scene or of a model opened in a block cache (which never
    waits for data). The Renderer classes below build on it."""
    cam = camera.to_native() if isinstance(camera, Camera) else camera
    image, depth, prim, stats = target.render(cam, render_params(params, **fields))
    return Frame(image, depth, prim, stats, 1, stats.milliseconds / 1000.0)


def average_passes(images: list[np.ndarray]) -> np.ndarray:
    """The image of a still view refined over passes: the mean of the images of passes
    0 .. K-1 (rendered with sample_index 0 .. K-1), rounded to 8 bits.

    Averaging finished images is exact up to rounding, because every pass shades the
    same hits and the indirect mode's filter weighs pixels by the guides (depth,
    normal) alone: each pass is a linear function of its noisy samples, so the mean of
    the filtered passes is the filtered mean of their samples. A server keeps a running
    sum (float32) and a count instead of the list."""
    if not images:
        raise ValueError("no passes to average")
    total = np.zeros(images[0].shape, dtype=np.float64)
    for image in images:
        if image.shape != total.shape:
            raise ValueError("passes of different sizes cannot be averaged")
        total += image
    return np.clip(np.rint(total / len(images)), 0, 255).astype(np.uint8)


@dataclass
class RayHits:
    """Full-detail answers to ray queries, one row per ray."""

    t: np.ndarray  # (n,) distance from the ray origin in world units; inf on a miss
    position: np.ndarray  # (n, 3) float64 world hit point; NaN on a miss
    normal: np.ndarray  # (n, 3) float32 unit geometric normal (0 on a miss)
    prim: np.ndarray  # (n,) int64 input triangle id; -1 on a miss
    complete: np.ndarray  # (n,) bool: False if the data the ray needed did not arrive in time


@runtime_checkable
class Renderer(Protocol):
    @property
    def name(self) -> str: ...

    @property
    def bounds(self) -> tuple[list[float], list[float]]: ...

    @property
    def triangle_count(self) -> int: ...

    def render(self, camera: Camera, params: native.RenderParams | None = None, **fields: Any) -> Frame:
        """One frame from what is available now (never waits for data)."""
        ...

    def render_complete(
        self,
        camera: Camera,
        params: native.RenderParams | None = None,
        *,
        timeout: float = 600.0,
        cancelled: Callable[[], bool] | None = None,
        **fields: Any,
    ) -> Frame:
        """A frame with nothing missing at the chosen accuracy (pixels_of_error 0: full
        detail). Raises TimeoutError after `timeout` seconds."""
        ...

    def pick(
        self, origins: np.ndarray, directions: np.ndarray, *, timeout: float = 10.0, sections: Sections = ()
    ) -> RayHits:
        """Full-detail closest hits of world rays, whatever level of detail frames use;
        section planes cut as they do in frames."""
        ...

    def close(self) -> None: ...


def open_renderer(
    source: str | os.PathLike[str],
    *,
    cache: native.BlockCache | None = None,
    on_phase: Callable[[str], None] | None = None,
    **build_options: Any,
) -> Renderer:
    """A renderer for `source`: a built model opens out of core in `cache` (the shared
    cache by default); a mesh, 'demo' or 'scene:…' is loaded and built in core."""
    from vastray.sources import is_model_file

    if is_model_file(source):
        from vastray.outofcore import OutOfCoreModel

        return OutOfCoreModel(source, cache)
    from vastray.render import load_model

    return load_model(str(source), on_phase=on_phase, **build_options)
