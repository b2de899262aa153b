"""In-core rendering: a mesh file, a procedural scene or a built model decoded whole,
as a native scene (its 8-wide BVH and kd-tree built on first use), behind the `Renderer` interface
(vastray/renderer.py). Always complete, always full detail: the reference the
out-of-core renderer is tested against, and the quick way to look at a mesh."""

from __future__ import annotations

import os
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from vastray import native
from vastray.camera import Camera
from vastray.mesh import Mesh
from vastray.renderer import Frame, RayHits, Sections, trace
from vastray.sources import MODEL_SUFFIX, SOURCE_HELP, is_model_file, parse_scene


class SceneRenderer:
    """An in-core scene. `load_seconds` and `build_seconds` say what opening it cost (the
    scene's own set-up; the structures its rays walk are built on first use)."""

    def __init__(self, scene: native.Scene, name: str, load_seconds: float = 0.0, build_seconds: float = 0.0):
        self.scene = scene
        self.name = name
        self.load_seconds = load_seconds
        self.build_seconds = build_seconds

    @property
    def bounds(self) -> tuple[list[float], list[float]]:
        return self.scene.bounds

    @property
    def triangle_count(self) -> int:
        return int(self.scene.triangle_count)

    def render(self, camera: Camera, params: native.RenderParams | None = None, **fields: Any) -> Frame:
        return trace(self.scene, camera, params, **fields)

    def render_complete(
        self,
        camera: Camera,
        params: native.RenderParams | None = None,
        *,
        timeout: float = 600.0,
        cancelled: Callable[[], bool] | None = None,
        **fields: Any,
    ) -> Frame:
        # In core every frame is complete.
        return self.render(camera, params, **fields)

    def pick(
        self, origins: np.ndarray, directions: np.ndarray, *, timeout: float = 10.0, sections: Sections = ()
    ) -> RayHits:
        o = np.ascontiguousarray(origins, dtype=np.float64).reshape(-1, 3)
        d = np.ascontiguousarray(directions, dtype=np.float64).reshape(-1, 3)
        length = np.linalg.norm(d, axis=1)
        out = self.scene.intersect(o, d, sections=list(sections))
        hit = out["prim"] >= 0
        # t counts lengths of the float direction; report world distances as the
        # out-of-core renderer does.
        t = np.where(hit, out["t"] * length, np.inf)
        position = np.full((len(o), 3), np.nan)
        position[hit] = o[hit] + d[hit] * out["t"][hit, None]
        return RayHits(t, position, out["normal"], out["prim"], np.ones(len(o), dtype=bool))

    def close(self) -> None:
        pass


def scene_from_mesh(mesh: Mesh, **build_options: Any) -> native.Scene:
    return native.Scene(mesh.vertices, mesh.faces, mesh.face_colours, mesh.triangle_ids,
                        **build_options)  # fmt: skip


def resolve_mesh(source: str) -> Mesh:
    """`demo`, `scene:NAME[:TRIANGLES[:SEED]]`, or a mesh file path."""
    from vastray import scenes
    from vastray.ingest import load_mesh

    scene = parse_scene(source)
    if scene is not None:
        return scenes.to_mesh(scene.name, scene.triangles, scene.seed)
    if not os.path.exists(source):
        raise FileNotFoundError(f"{source}: no such file (or use {SOURCE_HELP})")
    if source.lower().endswith(MODEL_SUFFIX):
        # Named as a model but not one: the model reader says what is wrong with it.
        from vastray.modelfile import ModelFile

        ModelFile(source).close()
    return load_mesh(source)


def load_model(
    source: str, *, on_phase: Callable[[str], None] | None = None, **build_options: Any
) -> SceneRenderer:
    """Load (or generate) a model as an in-core scene, or decode a built model at full
    detail. The structures rays walk are built on first use (`Scene.any_hit_stats()`
    builds the 8-wide BVH every frame walks; `Scene.build_stats` the kd-tree, which only
    VASTRAY_PRIMARY=kd or VASTRAY_ANYHIT=kd frames walk). `on_phase` hears about each
    phase as it starts, so a CLI or a job can tell the user what the wait is for."""
    start = time.perf_counter()
    if is_model_file(source):
        from vastray.modelfile import ModelFile

        if on_phase is not None:
            on_phase(f"decoding built model {source} at full detail")
        with ModelFile(source) as model_file:
            scene = model_file.to_scene()
        return SceneRenderer(scene, os.path.basename(source), time.perf_counter() - start)
    if on_phase is not None:
        on_phase(f"loading {source}")
    mesh = resolve_mesh(source)
    loaded = time.perf_counter()
    if on_phase is not None:
        on_phase(f"preparing {mesh.triangle_count:,} triangles")
    scene = scene_from_mesh(mesh, **build_options)
    return SceneRenderer(scene, mesh.name, loaded - start, time.perf_counter() - loaded)
