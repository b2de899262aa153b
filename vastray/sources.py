"""What a model argument names: the built-in demo, a procedural scene
(`scene:NAME[:TRIANGLES[:SEED]]`), or a file (a mesh, or a model written by
`vastray build`, told apart by its magic bytes). Every command and the server read
these names through this module."""

from __future__ import annotations

import os
from dataclasses import dataclass

# The built-in demo: a CAD-like plant, big enough to show the renderer, small enough to
# generate and build in seconds on a laptop.
DEMO = "demo"
DEMO_SCENE = "plant"
DEMO_TRIANGLES = 300_000
DEMO_SEED = 7
DEFAULT_SCENE_TRIANGLES = 100_000
SOURCE_HELP = "'demo' / 'scene:NAME:TRIANGLES:SEED'"
MODEL_SUFFIX = ".vast"  # what `vastray build` and the server name model files


@dataclass(frozen=True)
class SceneSource:
    name: str
    triangles: int
    seed: int

    @property
    def label(self) -> str:
        return f"{self.name}-{self.triangles}-s{self.seed}"


def parse_scene(source: str | os.PathLike[str]) -> SceneSource | None:
    """The procedural scene `source` names, or None when it names a file. Raises
    ValueError for a malformed or unknown scene."""
    from vastray import scenes

    text = str(source)
    if text == DEMO:
        return SceneSource(DEMO_SCENE, DEMO_TRIANGLES, DEMO_SEED)
    if not text.startswith("scene:"):
        return None
    parts = text.split(":")[1:]
    if not 1 <= len(parts) <= 3 or not parts[0]:
        raise ValueError(f"{text!r}: expected scene:NAME[:TRIANGLES[:SEED]]")
    try:
        triangles = int(float(parts[1])) if len(parts) > 1 else DEFAULT_SCENE_TRIANGLES
        seed = int(parts[2]) if len(parts) > 2 else 1
    except ValueError:
        raise ValueError(f"{text!r}: the triangle count and seed must be numbers") from None
    if parts[0] not in scenes.SCENES:
        raise ValueError(f"unknown scene {parts[0]!r}; choose one of {', '.join(scenes.SCENES)}")
    if triangles < 1:
        raise ValueError(f"{text!r}: the triangle count must be positive")
    return SceneSource(parts[0], triangles, seed)


def is_model_file(path: str | os.PathLike[str]) -> bool:
    """Whether `path` is a file written by `vastray build` (checked by its magic bytes,
    whatever its name)."""
    from vastray.modelfile import MAGIC

    try:
        with open(path, "rb") as f:
            return f.read(len(MAGIC)) == MAGIC
    except OSError:
        return False
