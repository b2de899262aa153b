"""Streaming readers for triangle inputs larger than memory: binary PLY, binary STL and
raw float32 triangle soup. Each yields bounded chunks of triangles, so a builder can
pass over a 10^8-triangle file holding one chunk at a time. Sequential data is read
with plain reads, not memory maps, so pages already processed never count towards the
process's resident memory; PLY vertices (indexed at random) are mapped one chunk at a
time.
(Ordinary sizes and other formats go through `vastray.ingest`, which uses trimesh.)"""

from __future__ import annotations

import os
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from vastray.mesh import MeshError

DEFAULT_CHUNK = 1 << 20  # triangles per chunk: 36 MB of float32 corners

_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}  # fmt: skip


@dataclass
class TriangleChunk:
    corners: np.ndarray  # (k, 3, 3) float64: three corners per triangle
    colours: np.ndarray | None  # (k, 3) uint8 per-face colour, when the file has it


class TriangleSource:
    """A triangle file opened for streaming: counts up front, chunks on demand."""

    def __init__(self, path: str | os.PathLike[str]) -> None:
        self.path = Path(path)
        self.triangle_count = 0
        self.has_colours = False

    def chunks(self, size: int = DEFAULT_CHUNK) -> Iterator[TriangleChunk]:
        raise NotImplementedError

    def vertex_bounds(self) -> tuple[np.ndarray, np.ndarray] | None:
        """Bounds of the file's vertices when they are cheaper to get than by reading
        every triangle (an indexed format), else None."""
        return None

    def _check(self, corners: np.ndarray, first: int) -> None:
        bad = ~np.isfinite(corners).all(axis=(1, 2))
        if bad.any():
            index = first + int(np.argmax(bad))
            raise MeshError(f"{self.path}: triangle {index} has a non-finite coordinate")


class RawSoupSource(TriangleSource):
    """Raw little-endian float32 triangle soup: 9 floats (three corners) per triangle."""

    def __init__(self, path: str | os.PathLike[str]) -> None:
        super().__init__(path)
        size = self.path.stat().st_size
        if size % 36 != 0:
            raise MeshError(f"{self.path}: raw soup size {size} is not a multiple of 36 bytes (9 float32)")
        self.triangle_count = size // 36

    def chunks(self, size: int = DEFAULT_CHUNK) -> Iterator[TriangleChunk]:
        if self.triangle_count == 0:
            return
        with open(self.path, "rb") as f:
            for first in range(0, self.triangle_count, size):
                count = min(size, self.triangle_count - first)
                data = np.fromfile(f, dtype="<f4", count=9 * count).reshape(count, 3, 3)
                corners = data.astype(np.float64)
                self._check(corners, first)
                yield TriangleChunk(corners, None)


class StlSource(TriangleSource):
    """Binary STL: 80-byte header, uint32 count, 50-byte records."""

    _RECORD = np.dtype([("normal", "<f4", (3,)), ("corners", "<f4", (3, 3)), ("attr", "<u2")])

    def __init__(self, path: str | os.PathLike[str]) -> None:
        super().__init__(path)
        size = self.path.stat().st_size
        with open(self.path, "rb") as f:
            head = f.read(84)
        if len(head) < 84:
            raise MeshError(f"{self.path}: too short for a binary STL header")
        if head[:5].lower() == b"solid" and size != 84 + 50 * int.from_bytes(head[80:84], "little"):
            raise MeshError(f"{self.path}: ASCII STL cannot be streamed (load it with vastray.ingest)")
        self.triangle_count = int.from_bytes(head[80:84], "little")
        expected = 84 + 50 * self.triangle_count
        if size < expected:
            raise MeshError(
                f"{self.path}: truncated: {size} bytes, {self.triangle_count} triangles need {expected}"
            )

    def chunks(self, size: int = DEFAULT_CHUNK) -> Iterator[TriangleChunk]:
        if self.triangle_count == 0:
            return
        with open(self.path, "rb") as f:
            f.seek(84)
            for first in range(0, self.triangle_count, size):
                count = min(size, self.triangle_count - first)
                records = np.fromfile(f, dtype=self._RECORD, count=count)
                corners = records["corners"].astype(np.float64)
                self._check(corners, first)
                yield TriangleChunk(corners, None)


class PlySource(TriangleSource):
    """Binary PLY (either byte order) with a vertex element holding x, y, z and a face
    element whose first property is the vertex-index list; faces must be triangles.
    Per-face red/green/blue are kept when present."""

    def __init__(self, path: str | os.PathLike[str]) -> None:
        super().__init__(path)
        with open(self.path, "rb") as f:
            header = b""
            while not header.endswith(b"end_header\n"):
                line = f.readline()
                if not line or len(header) > 1 << 16:
                    raise MeshError(f"{self.path}: no PLY end_header")
                header += line.replace(b"\r\n", b"\n")
            self._data_offset = f.tell()
        lines = header.decode("ascii", errors="replace").splitlines()
        if not lines or lines[0] != "ply":
            raise MeshError(f"{self.path}: not a PLY file")
        elements: list[tuple[str, int, list[list[str]]]] = []
        order = ""
        for line in lines[1:]:
            words = line.split()
            if not words or words[0] in ("comment", "obj_info", "end_header"):
                continue
            if words[0] == "format":
                order = {"binary_little_endian": "<", "binary_big_endian": ">"}.get(words[1], "")
                if not order:
                    raise MeshError(
                        f"{self.path}: {words[1]} PLY cannot be streamed (load it with vastray.ingest)"
                    )
            elif words[0] == "element":
                elements.append((words[1], int(words[2]), []))
            elif words[0] == "property" and elements:
                elements[-1][2].append(words[1:])
        self._order = order
        offset = self._data_offset
        self._vertex: tuple[int, int, np.dtype] | None = None
        self._face: tuple[int, int, np.dtype] | None = None
        for name, count, props in elements:
            dtype = self._element_dtype(name, props)
            if name == "vertex":
                self._vertex = (offset, count, dtype)
            elif name == "face":
                self._face = (offset, count, dtype)
            elif dtype is None:
                raise MeshError(f"{self.path}: element {name!r} has list properties; cannot skip it")
            offset += count * dtype.itemsize
        if self._vertex is None or self._face is None:
            raise MeshError(f"{self.path}: PLY needs vertex and face elements")
        if self.path.stat().st_size < offset:
            raise MeshError(
                f"{self.path}: truncated: {self.path.stat().st_size} bytes, header describes {offset}"
            )
        names = self._vertex[2].names or ()
        if not {"x", "y", "z"} <= set(names):
            raise MeshError(f"{self.path}: vertex element lacks x, y, z")
        self.triangle_count = self._face[1]
        self.has_colours = {"red", "green", "blue"} <= set(self._face[2].names or ())

    def _element_dtype(self, element: str, props: list[list[str]]) -> np.dtype:
        fields: list[tuple[str, str] | tuple[str, str, tuple[int]]] = []
        for prop in props:
            if prop[0] == "list":
                if element != "face" or fields:
                    raise MeshError(f"{self.path}: unsupported list property in element {element!r}")
                count_t, index_t = _PLY_TYPES.get(prop[1]), _PLY_TYPES.get(prop[2])
                if count_t is None or index_t is None:
                    raise MeshError(f"{self.path}: unknown PLY type in {' '.join(prop)}")
                # Triangles only: the list is then a fixed-size record field.
                fields += [("n", self._order + count_t), ("v", self._order + index_t, (3,))]
            else:
                t = _PLY_TYPES.get(prop[0])
                if t is None:
                    raise MeshError(f"{self.path}: unknown PLY type {prop[0]!r}")
                fields.append((prop[1], self._order + t))
        return np.dtype(fields)

    def chunks(self, size: int = DEFAULT_CHUNK) -> Iterator[TriangleChunk]:
        assert self._vertex is not None and self._face is not None
        v_off, v_count, v_dtype = self._vertex
        f_off, f_count, f_dtype = self._face
        if f_count == 0:
            return
        with open(self.path, "rb") as f:
            f.seek(f_off)
            for first in range(0, f_count, size):
                block = np.fromfile(f, dtype=f_dtype, count=min(size, f_count - first))
                if (block["n"] != 3).any():
                    index = first + int(np.argmax(block["n"] != 3))
                    raise MeshError(
                        f"{self.path}: face {index} is not a triangle; only triangle PLY can be streamed"
                    )
                idx = np.asarray(block["v"], dtype=np.int64)
                if (idx < 0).any() or (idx >= v_count).any():
                    index = first + int(np.argmax(((idx < 0) | (idx >= v_count)).any(axis=1)))
                    raise MeshError(f"{self.path}: face {index} references a vertex outside 0..{v_count - 1}")
                # Vertices are indexed at random: map them for this chunk only, so the
                # pages it touched leave the resident set when the map goes.
                vertices = np.memmap(self.path, dtype=v_dtype, mode="r", offset=v_off, shape=(v_count,))
                corners = np.stack(
                    [np.asarray(vertices[axis][idx], dtype=np.float64) for axis in "xyz"], axis=-1
                )
                del vertices
                self._check(corners, first)
                colours = (
                    np.stack([np.asarray(block[c], dtype=np.uint8) for c in ("red", "green", "blue")], axis=1)
                    if self.has_colours
                    else None
                )
                yield TriangleChunk(corners, colours)

    def vertex_bounds(self) -> tuple[np.ndarray, np.ndarray] | None:
        assert self._vertex is not None
        v_off, v_count, v_dtype = self._vertex
        lo, hi = np.full(3, np.inf), np.full(3, -np.inf)
        with open(self.path, "rb") as f:
            f.seek(v_off)
            for first in range(0, v_count, DEFAULT_CHUNK):
                block = np.fromfile(f, dtype=v_dtype, count=min(DEFAULT_CHUNK, v_count - first))
                xyz = np.stack([np.asarray(block[a], dtype=np.float64) for a in "xyz"], axis=1)
                if not np.isfinite(xyz).all():
                    index = first + int(np.argmax(~np.isfinite(xyz).all(axis=1)))
                    raise MeshError(f"{self.path}: vertex {index} has a non-finite coordinate")
                lo, hi = np.minimum(lo, xyz.min(axis=0)), np.maximum(hi, xyz.max(axis=0))
        return lo, hi


def open_triangles(path: str | os.PathLike[str]) -> TriangleSource:
    """Open a binary PLY, binary STL or raw float32 soup (.f32, .soup) for streaming."""
    p = Path(path)
    if not p.is_file():
        raise MeshError(f"{p}: no such file")
    ext = p.suffix.lower()
    if ext == ".ply":
        return PlySource(p)
    if ext == ".stl":
        return StlSource(p)
    if ext in (".f32", ".soup"):
        return RawSoupSource(p)
    raise MeshError(f"{p}: streaming reads .ply, .stl and raw float32 soup (.f32, .soup), not {ext!r}")
