"""Procedural test scenes, deterministic by seed, from 10^3 to 10^8+ triangles.

A scene is generated as an iterator of chunks ``(vertices, faces, face_colours)``:
vertices float64 (k, 3), faces uint32 (m, 3) indexing that chunk's vertices, colours
uint8 (m, 3) or None; no chunk has more than ``CHUNK_TRIANGLES`` triangles, so memory
stays bounded whatever the size. ``write_scene`` streams chunks to a binary PLY or STL.
All scenes are y-up and sit near the origin (float32 in files loses nothing visible).
"""

from __future__ import annotations

import os
import shutil
import tempfile
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO

import numpy as np

from vastray.mesh import Mesh, validate
from vastray.scenes._geom import CHUNK_TRIANGLES, Chunk
from vastray.scenes.mandelbulb import mandelbulb
from vastray.scenes.plant import PART_NAMES as PLANT_PARTS
from vastray.scenes.plant import part_of_colours as plant_part_of
from vastray.scenes.plant import plant
from vastray.scenes.spheres import spheres

__all__ = [
    "CHUNK_TRIANGLES",
    "MAX_TRIANGLES",
    "MIN_TRIANGLES",
    "SCENES",
    "Chunk",
    "SceneSpec",
    "generate",
    "to_mesh",
    "write_scene",
]

MIN_TRIANGLES = 1_000
MAX_TRIANGLES = 2_000_000_000  # a PLY/STL triangle count must fit in 32 bits


@dataclass(frozen=True)
class SceneSpec:
    name: str
    description: str
    coloured: bool
    generator: Callable[[int, int], Iterator[Chunk]]
    # Parts, for scenes that have them: their names, and the part of each triangle from
    # its colour (what `vastray build scene:...` stores; files written by write_scene
    # carry colours only).
    part_names: tuple[str, ...] = ()
    part_of: Callable[[np.ndarray], np.ndarray] | None = None


SCENES: dict[str, SceneSpec] = {
    spec.name: spec
    for spec in (
        SceneSpec(
            "spheres",
            "coloured UV spheres on a checkered ground; simple, mostly convex",
            True,
            spheres,
        ),
        SceneSpec(
            "plant",
            "industrial plant: thin pipes with elbows, flanges and bolts in steel frames",
            True,
            plant,
            PLANT_PARTS,
            plant_part_of,
        ),
        SceneSpec(
            "mandelbulb",
            "power-8 Mandelbulb isosurface (marching tetrahedra), coloured by orbit trap",
            True,
            mandelbulb,
        ),
    )
}


def _check_args(name: str, triangles: int, seed: int) -> SceneSpec:
    if name not in SCENES:
        raise ValueError(f"unknown scene {name!r}; choose one of {', '.join(SCENES)}")
    if isinstance(triangles, bool) or not isinstance(triangles, (int, np.integer)):
        raise TypeError(f"triangles must be an integer, got {triangles!r}")
    if not MIN_TRIANGLES <= triangles <= MAX_TRIANGLES:
        raise ValueError(f"triangles must be in [{MIN_TRIANGLES}, {MAX_TRIANGLES}], got {triangles}")
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ValueError(f"seed must be a non-negative integer, got {seed!r}")
    return SCENES[name]


def generate(name: str, triangles: int, seed: int) -> Iterator[Chunk]:
    """Chunks of scene ``name`` with about ``triangles`` triangles (within 5%)."""
    spec = _check_args(name, triangles, seed)
    return _checked(spec, int(triangles), int(seed))


def _checked(spec: SceneSpec, triangles: int, seed: int) -> Iterator[Chunk]:
    # Guards the chunk contract that the writers and the native build rely on.
    for vertices, faces, colours in spec.generator(triangles, seed):
        if faces.shape[0] > CHUNK_TRIANGLES or faces.dtype != np.uint32:
            raise RuntimeError(f"scene {spec.name} broke the chunk contract")
        if (colours is not None) != spec.coloured:
            raise RuntimeError(f"scene {spec.name} changed whether it has colours")
        yield vertices, faces, colours


def to_mesh(name: str, triangles: int, seed: int) -> Mesh:
    """The whole scene as one validated Mesh; for small scenes and tests."""
    vertices, faces, colours = [], [], []
    offset = 0
    for v, f, c in generate(name, triangles, seed):
        vertices.append(v)
        faces.append(f.astype(np.int64) + offset)
        colours.append(c)
        offset += v.shape[0]
    mesh = Mesh(
        vertices=np.concatenate(vertices),
        faces=np.concatenate(faces).astype(np.uint32),
        face_colours=None if colours[0] is None else np.concatenate(colours),
        name=f"{name}-{triangles}-s{seed}",
    )
    return validate(mesh, mesh.name)


# PLY header is written last, when the counts are known, into this many bytes reserved at
# the start of the file; a comment line pads it to the exact size.
_PLY_HEADER_BYTES = 512


def _ply_header(name: str, seed: int, vertices: int, faces: int, coloured: bool) -> bytes:
    lines = [
        "ply",
        "format binary_little_endian 1.0",
        f"comment vastray scene {name} seed {seed}",
        "PADDING",
        f"element vertex {vertices}",
        "property float x",
        "property float y",
        "property float z",
        f"element face {faces}",
        "property list uchar uint vertex_indices",
    ]
    if coloured:
        lines += ["property uchar red", "property uchar green", "property uchar blue"]
    lines.append("end_header")
    text = "\n".join(lines) + "\n"
    pad = _PLY_HEADER_BYTES - (len(text) - len("PADDING"))
    if pad < len("comment "):
        raise OverflowError("PLY header does not fit its reserved space")
    return text.replace("PADDING", "comment" + " " * (pad - len("comment"))).encode("ascii")


def _face_dtype(coloured: bool) -> np.dtype:
    fields: list[tuple[str, str] | tuple[str, str, tuple[int, ...]]] = [
        ("n", "u1"),
        ("v", "<u4", (3,)),
    ]
    if coloured:
        fields.append(("rgb", "u1", (3,)))
    return np.dtype(fields)


_STL_DTYPE = np.dtype([("normal", "<f4", (3,)), ("v", "<f4", (3, 3)), ("attr", "<u2")])


def _write_ply(
    out: BinaryIO,
    chunks: Iterator[Chunk],
    spec: SceneSpec,
    seed: int,
    progress: Callable[[int], None] | None,
    workdir: Path,
) -> tuple[int, int]:
    out.write(b"\0" * _PLY_HEADER_BYTES)
    n_vertices = n_faces = 0
    dtype = _face_dtype(spec.coloured)
    # PLY wants every vertex before any face, so faces wait in a side file.
    with tempfile.TemporaryFile(dir=workdir) as face_file:
        for vertices, faces, colours in chunks:
            out.write(np.ascontiguousarray(vertices, dtype="<f4").tobytes())
            records = np.empty(faces.shape[0], dtype=dtype)
            records["n"] = 3
            records["v"] = faces.astype(np.int64) + n_vertices
            if colours is not None:
                records["rgb"] = colours
            face_file.write(records.tobytes())
            n_vertices += vertices.shape[0]
            n_faces += faces.shape[0]
            if n_vertices >= 2**32:
                raise OverflowError("scene has too many vertices for a PLY with uint indices")
            if progress is not None:
                progress(faces.shape[0])
        face_file.seek(0)
        shutil.copyfileobj(face_file, out, 1 << 24)
    out.seek(0)
    out.write(_ply_header(spec.name, seed, n_vertices, n_faces, spec.coloured))
    return n_faces, n_vertices


def _write_stl(
    out: BinaryIO,
    chunks: Iterator[Chunk],
    spec: SceneSpec,
    seed: int,
    progress: Callable[[int], None] | None,
    workdir: Path,
) -> tuple[int, int]:
    header = f"vastray scene {spec.name} seed {seed}".encode("ascii")[:80]
    out.write(header.ljust(80, b" "))
    out.write(b"\0\0\0\0")
    n_faces = 0
    for vertices, faces, _ in chunks:
        tri = vertices[faces]  # (m, 3, 3)
        normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        length = np.linalg.norm(normal, axis=1, keepdims=True)
        records = np.zeros(faces.shape[0], dtype=_STL_DTYPE)
        records["normal"] = np.divide(normal, length, out=np.zeros_like(normal), where=length > 0)
        records["v"] = tri
        out.write(records.tobytes())
        n_faces += faces.shape[0]
        if progress is not None:
            progress(faces.shape[0])
    out.seek(80)
    out.write(np.uint32(n_faces).astype("<u4").tobytes())
    return n_faces, 3 * n_faces


_WRITERS = {".ply": _write_ply, ".stl": _write_stl}


def write_scene(
    name: str,
    triangles: int,
    seed: int,
    path: str | os.PathLike[str],
    progress: Callable[[int], None] | None = None,
) -> dict[str, int]:
    """Stream a scene to ``path``: binary little-endian PLY (``.ply``, with face colours
    when the scene has them) or binary STL (``.stl``, no colours).

    The file appears under its name only when complete; on any error or interrupt the
    partial file is removed. ``progress`` is called after each chunk with the number of
    triangles it added (suits ``tqdm.update``). Returns the triangle and vertex counts
    of the file (STL repeats vertices, 3 per triangle) and its size in bytes.
    """
    target = Path(path)
    writer = _WRITERS.get(target.suffix.lower())
    if writer is None:
        raise ValueError(f"{target}: scene output must end in .ply or .stl")
    spec = _check_args(name, triangles, seed)
    chunks = generate(name, triangles, seed)
    workdir = target.parent
    fd, tmp_name = tempfile.mkstemp(dir=workdir, prefix=f".{target.name}.", suffix=".part")
    try:
        with os.fdopen(fd, "w+b") as out:
            n_faces, n_vertices = writer(out, chunks, spec, int(seed), progress, workdir)
        # mkstemp creates 0600; give the finished file the permissions a plain open() would.
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp_name, 0o666 & ~umask)
        os.replace(tmp_name, target)
    except BaseException:
        # KeyboardInterrupt included: a half-written model must never look complete.
        Path(tmp_name).unlink(missing_ok=True)
        raise
    return {"triangles": n_faces, "vertices": n_vertices, "bytes": target.stat().st_size}
