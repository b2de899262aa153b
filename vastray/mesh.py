"""In-memory triangle mesh and the checks every ingested or generated mesh goes through.

The checks follow the design brief: non-finite coordinates and empty inputs are errors
(they would poison bounds and the spatial build), out-of-range indices are errors, and
zero-area triangles are dropped with a warning that says how many.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np

__all__ = ["DegenerateTrianglesWarning", "Mesh", "MeshError", "PartName", "validate"]

# Degenerate-triangle detection works in blocks so that a 10^8-triangle mesh does not
# need several (F, 3) float64 temporaries at once.
_BLOCK = 1 << 20


class MeshError(ValueError):
    """The input is not a usable triangle mesh; the message names the source."""


class DegenerateTrianglesWarning(UserWarning):
    """Zero-area triangles were dropped from a mesh."""


@dataclass(frozen=True)
class PartName:
    """What names a part of the input: OBJ object / group / material, an ASCII STL
    solid (object), glTF node / mesh (and primitive) / material."""

    object: str = ""
    group: str = ""
    material: str = ""


@dataclass
class Mesh:
    """Triangles with optional per-triangle colours and parts.

    Face ``i`` is ``faces[i]``; ingest keeps the file's order. ``triangle_ids[i]`` is its
    index in the input as the file holds it (after polygons and strips are triangulated
    in file order), so dropping a degenerate triangle renumbers no other; a renderer's or
    a built model's triangle ids are these. ``validate`` always sets it (a mesh made
    without ids numbers its faces 0 ... F - 1); ``input_triangles`` counts the input's
    triangles, dropped ones included.
    """

    vertices: np.ndarray  # (V, 3) float64
    faces: np.ndarray  # (F, 3) uint32
    face_colours: np.ndarray | None  # (F, 3) uint8, or None when the input has none
    name: str
    triangle_ids: np.ndarray | None = None  # (F,) uint32
    part_ids: np.ndarray | None = None  # (F,) uint32 index into parts, or None without parts
    parts: list[PartName] | None = None
    input_triangles: int | None = None

    @property
    def triangle_count(self) -> int:
        return int(self.faces.shape[0])

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Axis-aligned bounds (lo, hi) in float64 of the vertices the faces use.

        Unreferenced vertices are left out: files often carry stray points that would
        otherwise inflate the box the camera and the build work from.
        """
        if self.faces.shape[0] == 0:
            raise MeshError(f"{self.name}: empty mesh has no bounds")
        used = np.zeros(self.vertices.shape[0], dtype=bool)
        used[self.faces.ravel()] = True
        pts = np.asarray(self.vertices, dtype=np.float64)[used]
        return pts.min(axis=0), pts.max(axis=0)


def _nonzero_area(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    keep = np.empty(faces.shape[0], dtype=bool)
    for start in range(0, faces.shape[0], _BLOCK):
        f = faces[start : start + _BLOCK]
        a = vertices[f[:, 0]]
        e1 = vertices[f[:, 1]] - a
        e2 = vertices[f[:, 2]] - a
        keep[start : start + f.shape[0]] = np.cross(e1, e2).any(axis=1)
    return keep


def validate(mesh: Mesh, source: str) -> Mesh:
    """Check ``mesh`` and return a cleaned copy; ``source`` names it in every message.

    Raises MeshError for non-finite coordinates (naming the first bad vertex), for a mesh
    without triangles, for bad shapes and for face indices out of range. Drops triangles
    whose area is exactly zero in float64 (including repeated indices), keeps
    ``face_colours``, ``triangle_ids`` and ``part_ids`` aligned, and warns with
    DegenerateTrianglesWarning giving the count.
    """
    vertices = np.asarray(mesh.vertices)
    faces = np.asarray(mesh.faces)
    if vertices.ndim != 2 or vertices.shape[1] != 3:
        raise MeshError(f"{source}: vertices must have shape (V, 3), got {vertices.shape}")
    if faces.ndim != 2 or faces.shape[1] != 3:
        raise MeshError(f"{source}: faces must be triangles of shape (F, 3), got {faces.shape}")
    if not np.issubdtype(vertices.dtype, np.number):
        raise MeshError(f"{source}: vertex coordinates are not numbers ({vertices.dtype})")
    if faces.shape[0] and not np.issubdtype(faces.dtype, np.integer):
        raise MeshError(f"{source}: face indices are not integers ({faces.dtype})")
    vertices = vertices.astype(np.float64, copy=False)

    finite = np.isfinite(vertices).all(axis=1)
    if not finite.all():
        i = int(np.argmin(finite))
        x, y, z = (float(c) for c in vertices[i])
        raise MeshError(f"{source}: vertex {i} has a non-finite coordinate ({x!r}, {y!r}, {z!r})")
    if faces.shape[0] == 0:
        raise MeshError(f"{source}: empty mesh (no triangles)")

    n_vertices = vertices.shape[0]
    bad = (faces < 0) | (faces >= n_vertices)
    if bad.any():
        f, c = np.argwhere(bad)[0]
        raise MeshError(
            f"{source}: face {int(f)} refers to vertex {int(faces[f, c])}, "
            f"but there are only {n_vertices} vertices"
        )
    faces = faces.astype(np.uint32, copy=False)

    n_faces = faces.shape[0]
    ids = np.arange(n_faces, dtype=np.uint32) if mesh.triangle_ids is None else np.asarray(mesh.triangle_ids)
    if ids.shape != (n_faces,):
        raise MeshError(f"{source}: triangle_ids must have shape ({n_faces},), got {ids.shape}")
    if n_faces and (ids.min() < 0 or ids.max() >= 2**32):
        raise MeshError(f"{source}: triangle ids must fit in 32 bits")
    ids = ids.astype(np.uint32, copy=False)
    part_ids = None if mesh.part_ids is None else np.asarray(mesh.part_ids).astype(np.uint32, copy=False)
    if part_ids is not None and (
        part_ids.shape != (n_faces,)
        or mesh.parts is None
        or (n_faces and int(part_ids.max()) >= len(mesh.parts))
    ):
        raise MeshError(f"{source}: part_ids must index parts, one per face")
    input_triangles = n_faces if mesh.input_triangles is None else int(mesh.input_triangles)

    colours = mesh.face_colours
    if colours is not None:
        colours = np.asarray(colours)
        if colours.shape != (faces.shape[0], 3):
            raise MeshError(
                f"{source}: face_colours must have shape ({faces.shape[0]}, 3), got {colours.shape}"
            )
        colours = colours.astype(np.uint8, copy=False)

    keep = _nonzero_area(vertices, faces)
    dropped = int(keep.size - np.count_nonzero(keep))
    if dropped:
        if dropped == keep.size:
            raise MeshError(f"{source}: all {dropped} triangles are degenerate (zero area)")
        faces = faces[keep]
        ids = ids[keep]
        if colours is not None:
            colours = colours[keep]
        if part_ids is not None:
            part_ids = part_ids[keep]
        # stacklevel 2 points at whoever asked for validation, which is the useful place.
        warnings.warn(
            f"{source}: dropped {dropped} degenerate triangles",
            DegenerateTrianglesWarning,
            stacklevel=2,
        )
    return Mesh(
        vertices=vertices,
        faces=faces,
        face_colours=colours,
        name=mesh.name,
        triangle_ids=ids,
        part_ids=part_ids,
        parts=mesh.parts,
        input_triangles=input_triangles,
    )
