"""In-core rendering: turn a mesh file (or a built-in scene) into a native scene and
render frames of it."""

from __future__ import annotations

import os
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from vastray import native
from vastray.camera import Camera
from vastray.mesh import Mesh
from vastray.sources import SOURCE_HELP, is_model_file, parse_scene

SHADING_MODES = ("normal", "headlight", "sun", "ao")


@dataclass
class Model:
    scene: native.Scene
    name: str
    load_seconds: float
    build_seconds: float

    @property
    def bounds(self) -> tuple[list[float], list[float]]:
        return self.scene.bounds


@dataclass
class Frame:
    image: np.ndarray  # (H, W, 3) uint8
    depth: np.ndarray  # (H, W) float32, inf where nothing was hit
    prim: np.ndarray  # (H, W) int32, -1 where nothing was hit
    stats: dict[str, Any] = field(default_factory=dict)


def scene_from_mesh(mesh: Mesh, **build_options: Any) -> native.Scene:
    return native.Scene(mesh.vertices, mesh.faces, mesh.face_colours, **build_options)


def resolve_mesh(source: str) -> Mesh:
    """`demo`, `scene:NAME[:TRIANGLES[:SEED]]`, or a mesh file path."""
    from vastray import scenes
    from vastray.ingest import load_mesh

    scene = parse_scene(source)
    if scene is not None:
        return scenes.to_mesh(scene.name, scene.triangles, scene.seed)
    if not os.path.exists(source):
        raise FileNotFoundError(f"{source}: no such file (or use {SOURCE_HELP})")
    return load_mesh(source)


def load_model(source: str, *, on_phase: Callable[[str], None] | None = None, **build_options: Any) -> Model:
    """Load (or generate) a model and build its kd-tree, or decode a built model at full
    detail. `on_phase` hears about each phase as it starts, so a CLI or a job can tell
    the user what the wait is for."""
    start = time.perf_counter()
    if is_model_file(source):
        from vastray.modelfile import ModelFile

        if on_phase is not None:
            on_phase(f"decoding built model {source} at full detail")
        with ModelFile(source) as model_file:
            scene = model_file.to_scene()
        decoded = time.perf_counter() - start
        return Model(scene=scene, name=os.path.basename(source), load_seconds=decoded, build_seconds=0.0)
    if on_phase is not None:
        on_phase(f"loading {source}")
    mesh = resolve_mesh(source)
    loaded = time.perf_counter()
    if on_phase is not None:
        on_phase(f"building kd-tree over {mesh.triangle_count:,} triangles")
    scene = scene_from_mesh(mesh, **build_options)
    built = time.perf_counter()
    return Model(scene=scene, name=mesh.name, load_seconds=loaded - start, build_seconds=built - loaded)


def render(
    model: Model | native.Scene,
    camera: Camera,
    *,
    shading: str = "headlight",
    ao_samples: int = 8,
    threads: int = 0,
) -> Frame:
    # The native renderer validates the camera and shading name (ValueError with the reason).
    scene = model.scene if isinstance(model, Model) else model
    out = scene.render(
        **camera.native_args(),
        shading=shading,
        ao_samples=ao_samples,
        threads=threads,
    )
    return Frame(image=out["image"], depth=out["depth"], prim=out["prim"], stats=out["stats"])
