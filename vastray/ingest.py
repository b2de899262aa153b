"""Loading ordinary-sized meshes (OBJ, PLY, STL, glTF/GLB, OFF) through trimesh.

Triangle ids follow the file: nothing is merged, reordered or repaired on the way in
(``process=False``; OBJ additionally keeps its ``v`` numbering, so vertex ``i`` in an
error message is line ``i`` of the file's vertex list, counting from 0).

Colours: a mesh gets ``face_colours`` only when the file states colours.
- explicit per-face colours are kept as they are (RGB; alpha is dropped);
- per-vertex colours are averaged over each triangle's three corners, because the
  renderer shades per triangle and a mean is the least surprising single value;
- a part whose material gives one explicit colour and no texture (OBJ ``Kd``, glTF
  ``baseColorFactor``) colours all its triangles with it;
- textures are not sampled: a textured part counts as uncoloured.
trimesh reports a grey default for meshes without colours; that is never stored. In a
file with several parts where only some are coloured, the others get white, which is
what glTF specifies for a primitive without material.

Limitation: files that trimesh splits into several parts (multi-material OBJ, glTF with
several nodes) come out part by part, in the order the file lists its geometries, so
triangle ids follow that order rather than the raw face order of the file.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import trimesh

from vastray.mesh import Mesh, MeshError, validate

__all__ = ["SUPPORTED_EXTENSIONS", "load_mesh"]

# Maps a file extension to trimesh's file_type.
SUPPORTED_EXTENSIONS: dict[str, str] = {
    ".obj": "obj",
    ".ply": "ply",
    ".stl": "stl",
    ".gltf": "gltf",
    ".glb": "glb",
    ".off": "off",
}

_WHITE = np.array([255, 255, 255], dtype=np.uint8)


def _material_colour(material: object) -> np.ndarray | None:
    if isinstance(material, trimesh.visual.material.PBRMaterial):
        if material.baseColorTexture is not None or material.baseColorFactor is None:
            return None
        return np.asarray(material.baseColorFactor, dtype=np.uint8)[:3]
    if isinstance(material, trimesh.visual.material.SimpleMaterial):
        # trimesh fills a grey diffuse for OBJ files without an .mtl; only a Kd the
        # file actually wrote shows up in the material's keyword record.
        explicit = "kd" in (getattr(material, "kwargs", None) or {})
        if not explicit or material.image is not None:
            return None
        return np.asarray(material.diffuse, dtype=np.uint8)[:3]
    return None


def _part_colours(geometry: trimesh.Trimesh) -> np.ndarray | None:
    """Per-face RGB colours the file really states for one part, else None."""
    visual = geometry.visual
    n_faces = len(geometry.faces)
    if isinstance(visual, trimesh.visual.ColorVisuals):
        # kind is None unless the loader stored colours; trimesh's grey default does
        # not count.
        if visual.kind == "face":
            return np.asarray(visual.face_colors, dtype=np.uint8)[:, :3].copy()
        if visual.kind == "vertex":
            vc = np.asarray(visual.vertex_colors, dtype=np.float64)[:, :3]
            mean = vc[np.asarray(geometry.faces)].mean(axis=1)
            return np.clip(np.rint(mean), 0, 255).astype(np.uint8)
        return None
    if isinstance(visual, trimesh.visual.TextureVisuals):
        colour = _material_colour(visual.material)
        if colour is None:
            return None
        return np.tile(colour, (n_faces, 1))
    return None


def _scene_parts(scene: trimesh.Scene) -> list[tuple[trimesh.Trimesh, np.ndarray]]:
    """(geometry, 4x4 transform) for every placed triangle mesh, in file geometry order."""
    nodes_by_geometry: dict[str, list[str]] = {}
    for node in scene.graph.nodes_geometry:
        _, geometry_name = scene.graph[node]
        nodes_by_geometry.setdefault(geometry_name, []).append(node)
    parts = []
    for geometry_name, geometry in scene.geometry.items():
        if not isinstance(geometry, trimesh.Trimesh):
            continue
        for node in nodes_by_geometry.get(geometry_name, []):
            transform, _ = scene.graph[node]
            parts.append((geometry, np.asarray(transform, dtype=np.float64)))
    return parts


def _to_mesh(loaded: object, name: str) -> Mesh:
    if isinstance(loaded, trimesh.Trimesh):
        parts = [(loaded, np.eye(4))]
    elif isinstance(loaded, trimesh.Scene):
        parts = _scene_parts(loaded)
    else:
        # Point clouds and line drawings have no triangles: report them as empty.
        parts = []

    vertices, faces, colours = [], [], []
    offset = 0
    for geometry, transform in parts:
        v = np.asarray(geometry.vertices, dtype=np.float64)
        f = np.asarray(geometry.faces, dtype=np.int64).reshape(-1, 3)
        if not np.array_equal(transform, np.eye(4)):
            v = v @ transform[:3, :3].T + transform[:3, 3]
        vertices.append(v)
        faces.append(f + offset)
        colours.append(_part_colours(geometry))
        offset += v.shape[0]

    if not parts:
        return Mesh(np.zeros((0, 3)), np.zeros((0, 3), np.uint32), None, name)
    face_colours = None
    if any(c is not None for c in colours):
        face_colours = np.concatenate(
            [
                c if c is not None else np.tile(_WHITE, (len(f), 1))
                for c, f in zip(colours, faces, strict=True)
            ]
        )
    return Mesh(
        vertices=np.concatenate(vertices).reshape(-1, 3),
        faces=np.concatenate(faces).reshape(-1, 3),
        face_colours=face_colours,
        name=name,
    )


def load_mesh(path: str | os.PathLike[str]) -> Mesh:
    """Load a mesh file and validate it (see ``vastray.mesh.validate``).

    Raises MeshError, naming the path, for a missing file, an unsupported extension, a
    file trimesh cannot parse, and for everything ``validate`` rejects.
    """
    p = Path(path)
    source = str(p)
    ext = p.suffix.lower()
    file_type = SUPPORTED_EXTENSIONS.get(ext)
    if file_type is None:
        supported = ", ".join(sorted(SUPPORTED_EXTENSIONS))
        raise MeshError(f"{source}: unsupported file extension {ext!r} (supported: {supported})")
    if not p.exists():
        raise MeshError(f"{source}: no such file")
    if not p.is_file():
        raise MeshError(f"{source}: not a regular file")

    kwargs: dict[str, object] = {}
    if file_type == "obj":
        # Keeps vertex numbering as in the file; otherwise trimesh splits vertices at
        # texture seams and renumbers them, and error messages would not match lines.
        kwargs["maintain_order"] = True
    try:
        loaded = trimesh.load(source, file_type=file_type, process=False, **kwargs)
    except Exception as exc:  # trimesh raises many types for malformed input
        raise MeshError(f"{source}: cannot parse as {file_type.upper()}: {exc}") from exc
    return validate(_to_mesh(loaded, p.name), source)
