"""Loading whole meshes (OBJ, PLY, STL, glTF/GLB, OFF, raw float32 soup) for in-core use.

The file is read by the same streaming readers the builder uses (vastray.triangle_readers),
its chunks collected into one `Mesh`, so a mesh loaded here and a model built from the
same file agree on every triangle: its vertices, colour, part and id. Nothing is merged,
reordered or repaired on the way in: an indexed file keeps its vertex numbering (vertex
`i` in an error message is the file's vertex `i`, counting from 0), a soup (STL, raw) has
three vertices per triangle. `validate` then drops degenerate triangles and warns; the
others keep their ids (`Mesh.triangle_ids`).

Colours and parts follow vastray.triangle_readers: a mesh gets `face_colours` only when
the file states colours (face colours, vertex colours averaged per triangle, untextured
material colours), and `part_ids`/`parts` when the file names parts (OBJ o/g/usemtl,
ASCII STL solids, glTF nodes).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from vastray.mesh import Mesh, MeshError, PartName, validate
from vastray.triangle_readers import STREAMED_EXTENSIONS, open_triangles

__all__ = ["SUPPORTED_EXTENSIONS", "load_mesh"]

# Maps a file extension to the format it is read as.
SUPPORTED_EXTENSIONS: dict[str, str] = STREAMED_EXTENSIONS


def load_mesh(path: str | os.PathLike[str]) -> Mesh:
    """Load a mesh file and validate it (see ``vastray.mesh.validate``).

    Raises MeshError, naming the path, for a missing file, an unsupported extension, a
    file that cannot be parsed, and for everything ``validate`` rejects.
    """
    p = Path(path)
    source_name = str(p)
    ext = p.suffix.lower()
    if ext not in SUPPORTED_EXTENSIONS:
        supported = ", ".join(sorted(SUPPORTED_EXTENSIONS))
        raise MeshError(f"{source_name}: unsupported file extension {ext!r} (supported: {supported})")
    if not p.exists():
        raise MeshError(f"{source_name}: no such file")
    if not p.is_file():
        raise MeshError(f"{source_name}: not a regular file")

    source = open_triangles(p)
    chunks = list(source.chunks())
    if source.vertices is not None:
        table = source.vertices
        vertices = table.xyz(table.buffer())
        faces = (
            np.concatenate([c.indices for c in chunks if c.indices is not None])
            if chunks
            else np.zeros((0, 3), np.int64)
        )
    else:
        corners = np.concatenate([c.corners for c in chunks]) if chunks else np.zeros((0, 3, 3))
        vertices = corners.reshape(-1, 3)
        faces = np.arange(len(vertices), dtype=np.int64).reshape(-1, 3)
    colours = None
    if source.has_colours and chunks:
        colours = np.concatenate([c.colours for c in chunks if c.colours is not None])
    # One unnamed part (an OBJ without o, g or usemtl) names nothing.
    parts = source.parts if source.parts and source.parts != [PartName()] else None
    part_ids = None
    if parts is not None and chunks:
        part_ids = np.concatenate([c.parts for c in chunks if c.parts is not None])
    ids = np.concatenate([c.triangle_ids for c in chunks]) if chunks else np.zeros(0, np.uint32)
    mesh = Mesh(
        vertices=vertices,
        faces=faces,
        face_colours=colours,
        name=p.name,
        triangle_ids=ids,
        part_ids=part_ids,
        parts=parts,
        input_triangles=source.triangle_count,
    )
    return validate(mesh, source_name)
