"""Streaming readers for every supported mesh format: OBJ, PLY (ASCII and binary of
either byte order; faces, polygons and triangle strips), STL (binary and ASCII), OFF,
glTF/GLB and raw float32 triangle soup. Each yields bounded chunks of triangles, so the
builder can pass over a file of any size holding one chunk at a time, and
`vastray.ingest.load_mesh` collects the same chunks into one mesh: a file's triangles,
their ids, colours and parts are the same on both paths.

Triangle ids. A triangle's id is its index in the input as the file holds it, after
polygons and strips are triangulated in file order (a polygon of n corners gives n - 2
triangles as a fan from its first corner; a strip gives one per corner after the
second, restarting at -1). Degenerate triangles keep their ids: they are dropped later
and counted, and no other triangle is renumbered.

Chunks are either soups (three float64 corners per triangle) or indexed (three vertex
indices into the source's `VertexTable`, which the builder gathers natively). Text
formats and indexed formats whose vertices are not stored in place are first scanned
once: their vertices (and OBJ/ASCII PLY/OFF triangles) are staged as binary arrays, in
memory or in a scratch folder, so the second pass reads binary records in order.
Sequential data is read with plain reads, not kept memory maps, so pages already
processed never count towards the process's resident memory; vertices (read at
random) are mapped one chunk at a time.

Colours, per triangle, when the file states any: a face colour (PLY, OFF), else the mean
of the corners' vertex colours (PLY, OBJ `v x y z r g b`, OFF, glTF COLOR_0), else the
colour of the triangle's material when it is one explicit colour without a texture (OBJ
`Kd`, glTF `baseColorFactor`); triangles without any in a file that has some are white
(glTF's default for a primitive without material). Parts: OBJ `o`/`g`/`usemtl`, the
solids of an ASCII STL, glTF's node/mesh/material and a PLY integer face property
(`part`, `part_id`, `object_id` or `group`; a part per value, named "part <value>")
give each triangle a part index into `parts` (a `PartName` per part, in order of first
use).
"""

from __future__ import annotations

import base64
import json
import os
import struct
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from vastray import native
from vastray.mesh import MeshError, PartName

DEFAULT_CHUNK = 1 << 20  # triangles per chunk: 36 MB of float32 corners
TEXT_BLOCK = 1 << 24  # bytes of text (or variable-size binary rows) parsed per native call
MAX_VERTICES = 2**32 - 1  # staged triangles index vertices with uint32

Progress = Callable[[int, int], None]  # (bytes done, bytes in all) while a file is scanned

_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}  # fmt: skip
_WHITE = np.array([255, 255, 255], dtype=np.uint8)
# Integer PLY face properties that give a triangle's part, the first one present wins.
PLY_PART_PROPERTIES = ("part", "part_id", "object_id", "group")


class VertexTable:
    """`count` vertex records of `stride` bytes; coordinate k at byte `offsets[k]`, of type
    `types[k]` ('<f4', '>f4', '<f8', '>f8'). The records lie in a file (at `offset`, mapped
    afresh by each `buffer()` call) or in an array. `colours`: (count, 3) uint8 vertex
    colours, or None."""

    def __init__(
        self,
        count: int,
        stride: int,
        offsets: tuple[int, int, int],
        types: tuple[str, str, str],
        *,
        array: np.ndarray | None = None,
        path: Path | None = None,
        offset: int = 0,
        colours: np.ndarray | None = None,
    ) -> None:
        self.count, self.stride, self.offsets, self.types = count, stride, offsets, types
        self._array, self._path, self._offset = array, path, offset
        self.colours = colours
        names = ["x", "y", "z"]
        self.dtype = np.dtype(
            {"names": names, "formats": list(types), "offsets": list(offsets), "itemsize": stride}
        )

    def buffer(self) -> np.ndarray:
        """The records as bytes (a fresh read-only map of the file region, or the array)."""
        if self._array is not None:
            return self._array.reshape(-1).view(np.uint8)
        if self.count == 0:
            return np.zeros(0, dtype=np.uint8)
        return np.memmap(
            self._path, dtype=np.uint8, mode="r", offset=self._offset, shape=(self.count * self.stride,)
        )

    def xyz(self, buffer: np.ndarray, start: int = 0, stop: int | None = None) -> np.ndarray:
        """Vertices start ... stop as (k, 3) float64."""
        stop = self.count if stop is None else stop
        rec = buffer[start * self.stride : stop * self.stride].view(self.dtype)
        return np.stack([rec[a].astype(np.float64) for a in ("x", "y", "z")], axis=1)

    def gather(self, buffer: np.ndarray, indices: np.ndarray) -> np.ndarray:
        """Corners (k, 3, 3) float64 of triangles given as vertex indices (k, 3)."""
        rec = buffer.view(self.dtype)
        return np.stack([rec[a][indices].astype(np.float64) for a in ("x", "y", "z")], axis=-1)


class TriangleChunk:
    """Triangles first ... first + count - 1 of the input (ids: explicit when the source
    left some out, as a validated mesh does). Soups give `corners`; indexed sources give
    `indices` into `vertices` (`corners` then gathers them on demand)."""

    def __init__(
        self,
        first: int,
        count: int,
        *,
        corners: np.ndarray | None = None,
        indices: np.ndarray | None = None,
        vertices: VertexTable | None = None,
        colours: np.ndarray | None = None,
        parts: np.ndarray | None = None,
        ids: np.ndarray | None = None,
    ) -> None:
        self.first, self.count = first, count
        self._corners, self.indices, self.vertices = corners, indices, vertices
        self.colours, self.parts, self.ids = colours, parts, ids

    @property
    def corners(self) -> np.ndarray:
        if self._corners is None:
            assert self.indices is not None and self.vertices is not None
            self._corners = self.vertices.gather(self.vertices.buffer(), self.indices)
        return self._corners

    @property
    def triangle_ids(self) -> np.ndarray:
        if self.ids is not None:
            return self.ids
        return np.arange(self.first, self.first + self.count, dtype=np.uint64)


class TriangleSource:
    """A triangle file opened for streaming. `triangle_count` is exact when `exact_count`
    (else an estimate until the chunks have been read: polygons and strips triangulate
    into more triangles than the file has faces)."""

    def __init__(self, path: str | os.PathLike[str]) -> None:
        self.path = Path(path)
        self.triangle_count = 0
        self.exact_count = True
        self.has_colours = False
        self.parts: list[PartName] | None = None
        self.vertices: VertexTable | None = None  # indexed sources

    def chunks(self, size: int = DEFAULT_CHUNK) -> Iterator[TriangleChunk]:
        raise NotImplementedError

    def vertex_bounds(self) -> tuple[np.ndarray, np.ndarray] | None:
        """Bounds of the file's vertices when they are cheaper to get than by reading
        every triangle (an indexed format), else None. Checks every vertex is finite."""
        if self.vertices is None:
            return None
        return _table_bounds(self.vertices, self.path)

    def fail(self, what: str) -> MeshError:
        return MeshError(f"{self.path}: {what}")

    def _check(self, corners: np.ndarray, first: int) -> None:
        bad = ~np.isfinite(corners).all(axis=(1, 2))
        if bad.any():
            raise self.fail(f"triangle {first + int(np.argmax(bad))} has a non-finite coordinate")


def _table_bounds(table: VertexTable, path: Path) -> tuple[np.ndarray, np.ndarray]:
    if table.count == 0:
        return np.full(3, np.inf), np.full(3, -np.inf)
    buffer = table.buffer()
    lo, hi, bad = native.vertex_bounds(buffer, table.stride, table.offsets, table.types, table.count)
    if bad >= 0:
        _check_vertices(table.xyz(buffer, bad, bad + 1), bad, lambda what: MeshError(f"{path}: {what}"))
    return np.array(lo), np.array(hi)


def _check_vertices(xyz: np.ndarray, first: int, fail: Callable[[str], MeshError]) -> None:
    """Raises for the first vertex with a non-finite coordinate (numbered as the file does)."""
    finite = np.isfinite(xyz).all(axis=1)
    if not finite.all():
        i = int(np.argmin(finite))
        x, y, z = (float(c) for c in xyz[i])
        raise fail(f"vertex {first + i} has a non-finite coordinate ({x!r}, {y!r}, {z!r})")


def _triangle_colours(
    table: VertexTable, indices: np.ndarray, face_rgb_flag: np.ndarray | None
) -> np.ndarray:
    """Per triangle: its face colour (rows of r, g, b, flag; flag 0: none), else the mean
    of its corners' vertex colours, else white."""
    if face_rgb_flag is not None and face_rgb_flag[:, 3].all():
        return face_rgb_flag[:, :3]  # a view; the record maker reads strided rows
    out = np.tile(_WHITE, (len(indices), 1))
    if table.colours is not None:
        corners = np.asarray(table.colours)[np.clip(indices, 0, table.count - 1)]
        out = np.rint(corners.astype(np.float64).mean(axis=1)).astype(np.uint8)
    if face_rgb_flag is not None:
        has = face_rgb_flag[:, 3] != 0
        out[has] = face_rgb_flag[has, :3]
    return out


# ---- staging ---------------------------------------------------------------------------------


class _Stage:
    """What a scan pass parsed, as binary arrays: in memory, or appended to files in a
    scratch folder (the builder's), so a file of any size stages within the budget."""

    def __init__(self, directory: Path | None, stem: str) -> None:
        self.directory, self.stem = directory, stem
        self._parts: dict[str, list[np.ndarray]] = {}
        self._files: dict[str, Any] = {}
        self.lengths: dict[str, int] = {}
        self.dtypes: dict[str, np.dtype] = {}

    def append(self, key: str, array: np.ndarray) -> None:
        # One row per element of the first axis, so files read back row by row.
        row = np.dtype((array.dtype, array.shape[1:])) if array.ndim > 1 else array.dtype
        self.dtypes.setdefault(key, row)
        self.lengths[key] = self.lengths.get(key, 0) + len(array)
        if self.directory is None:
            self._parts.setdefault(key, []).append(array)
            return
        f = self._files.get(key)
        if f is None:
            f = self._files[key] = open(self.directory / f"{self.stem}.{key}", "wb")
        np.ascontiguousarray(array).tofile(f)

    def close(self) -> None:
        for f in self._files.values():
            f.close()

    def path(self, key: str) -> Path:
        assert self.directory is not None
        return self.directory / f"{self.stem}.{key}"

    def array(self, key: str, shape_tail: tuple[int, ...] = ()) -> np.ndarray | None:
        """The staged array in memory, or None when it is on disk (or was never staged)."""
        if key not in self.lengths or self.directory is not None:
            return None
        parts = self._parts[key]
        return np.concatenate(parts).reshape(-1, *shape_tail) if len(parts) != 1 else parts[0]

    def rows(self, keys: list[str], size: int) -> Iterator[list[np.ndarray | None]]:
        """Several staged arrays in lockstep, `size` rows at a time (None for a key never
        staged)."""
        readers = [self.reader(k, size) if k in self.lengths else None for k in keys]
        lead = readers[0]
        assert lead is not None
        for first in lead:
            yield [first, *(None if r is None else next(r) for r in readers[1:])]

    def reader(self, key: str, size: int) -> Iterator[np.ndarray]:
        """The staged array in order, `size` rows at a time."""
        if key not in self.lengths:
            return
        if self.directory is None:
            whole = np.concatenate(self._parts[key]) if len(self._parts[key]) != 1 else self._parts[key][0]
            for start in range(0, len(whole), size):
                yield whole[start : start + size]
            return
        with open(self.path(key), "rb") as f:
            while len(block := np.fromfile(f, dtype=self.dtypes[key], count=size)):
                yield block

    def vertex_table(self, key: str, count: int, colours_key: str | None) -> VertexTable:
        colours = None
        if colours_key is not None and colours_key in self.lengths:
            colours = (
                self.array(colours_key, (3,))
                if self.directory is None
                else np.memmap(self.path(colours_key), dtype=np.uint8, mode="r", shape=(count, 3))
            )
        if self.directory is None:
            array = self.array(key, (3,)) if key in self.lengths else np.zeros((0, 3))
            return VertexTable(count, 24, (0, 8, 16), ("<f8", "<f8", "<f8"), array=array, colours=colours)
        return VertexTable(count, 24, (0, 8, 16), ("<f8", "<f8", "<f8"), path=self.path(key), colours=colours)


def _text_blocks(
    path: Path, start: int, progress: Progress | None, block: int = TEXT_BLOCK
) -> Iterator[tuple[bytes | memoryview, bool]]:
    """The file from byte `start` in blocks of whole lines: (data, at the end). The last
    block has at the end set (it may be empty). A line continued by a backslash stays in
    one block."""
    total = path.stat().st_size
    done = start
    with open(path, "rb") as f:
        f.seek(start)
        carry = b""
        while True:
            data = f.read(block)
            done += len(data)
            if not data:
                yield carry, True
                return
            data = carry + data
            cut = len(data)
            while True:  # the last newline that a backslash does not continue
                cut = data.rfind(b"\n", 0, cut)
                before = cut - 1 if cut > 0 and data[cut - 1 : cut] == b"\r" else cut
                if cut < 0 or data[before - 1 : before] != b"\\":
                    break
            if cut < 0:
                carry = data
                continue
            carry = data[cut + 1 :]
            if progress is not None:
                progress(done - len(carry), total)
            yield memoryview(data)[: cut + 1], False  # no copy of the block


class _RowStream:
    """Rows parsed from a stream of blocks: each parse call sees the unparsed rest of the
    current block; a row cut off by its end waits for the next block."""

    def __init__(
        self, blocks: Iterator[tuple[bytes | memoryview, bool]], start: int, fail: Callable[[str], MeshError]
    ) -> None:
        self.blocks, self.fail = blocks, fail
        self.data, self.at_end = next(blocks, (b"", True))
        self.at = 0
        self.offset = start  # the file offset of data[0]

    def rows(
        self, count: int, parse: Callable[[memoryview, int, bool], dict[str, Any]], what: str
    ) -> Iterator[tuple[dict[str, Any], int]]:
        """(parsed rows, index of their first) until `count` rows of `what` are parsed."""
        done = 0
        while done < count:
            rows = parse(memoryview(self.data)[self.at :], count - done, self.at_end)
            if rows["error"] is not None:
                raise self.fail(f"{what} {done + rows['error'][0] - 1}: {rows['error'][1]}")
            if rows["rows"]:
                yield rows, done
                done += rows["rows"]
                self.at += rows["consumed"]
                continue
            if self.at_end:
                raise self.fail(f"truncated: the file ends at {what} {done} of {count}")
            more, self.at_end = next(self.blocks, (b"", True))
            self.offset += self.at
            self.data, self.at = bytes(memoryview(self.data)[self.at :]) + more, 0

    @property
    def position(self) -> int:
        """The file offset of the first unparsed byte."""
        return self.offset + self.at


def _ply_parser(
    props: list[tuple[list[str], bool]], fmt: str
) -> Callable[[memoryview, int, bool], dict[str, Any]]:
    return lambda data, rows, at_end: native.ply_rows(data, rows, props, fmt, at_end)


# ---- raw soup and STL ------------------------------------------------------------------------


class RawSoupSource(TriangleSource):
    """Raw little-endian float32 triangle soup: 9 floats (three corners) per triangle."""

    def __init__(self, path: str | os.PathLike[str]) -> None:
        super().__init__(path)
        size = self.path.stat().st_size
        if size % 36 != 0:
            raise self.fail(f"raw soup size {size} is not a multiple of 36 bytes (9 float32)")
        self.triangle_count = size // 36

    def chunks(self, size: int = DEFAULT_CHUNK) -> Iterator[TriangleChunk]:
        with open(self.path, "rb") as f:
            for first in range(0, self.triangle_count, size):
                count = min(size, self.triangle_count - first)
                corners = np.fromfile(f, dtype="<f4", count=9 * count).reshape(count, 3, 3).astype(np.float64)
                self._check(corners, first)
                yield TriangleChunk(first, count, corners=corners)


class StlSource(TriangleSource):
    """Binary STL: 80-byte header, uint32 count, 50-byte records."""

    _RECORD = np.dtype([("normal", "<f4", (3,)), ("corners", "<f4", (3, 3)), ("attr", "<u2")])

    def __init__(self, path: str | os.PathLike[str]) -> None:
        super().__init__(path)
        size = self.path.stat().st_size
        with open(self.path, "rb") as f:
            head = f.read(84)
        if len(head) < 84:
            raise self.fail("too short for a binary STL header")
        self.triangle_count = int.from_bytes(head[80:84], "little")
        expected = 84 + 50 * self.triangle_count
        if size < expected:
            raise self.fail(f"truncated: {size} bytes, {self.triangle_count} triangles need {expected}")

    def chunks(self, size: int = DEFAULT_CHUNK) -> Iterator[TriangleChunk]:
        with open(self.path, "rb") as f:
            f.seek(84)
            for first in range(0, self.triangle_count, size):
                count = min(size, self.triangle_count - first)
                corners = np.fromfile(f, dtype=self._RECORD, count=count)["corners"].astype(np.float64)
                self._check(corners, first)
                yield TriangleChunk(first, count, corners=corners)


class AsciiStlSource(TriangleSource):
    """ASCII STL ("solid ... facet normal ... outer loop / vertex x y z / ..."): facets
    in file order; each `solid` starts a part named after it."""

    _BYTES_PER_FACET = 250  # typical, for the estimate before a pass has counted them

    def __init__(self, path: str | os.PathLike[str]) -> None:
        super().__init__(path)
        self.triangle_count = max(1, self.path.stat().st_size // self._BYTES_PER_FACET)
        self.exact_count = False
        self.parts = []

    def chunks(self, size: int = DEFAULT_CHUNK) -> Iterator[TriangleChunk]:
        first = line = 0
        parts: list[PartName] = []
        current = -1  # the solid in force; -1 before the first one
        left = b""  # a facet cut off by the end of the last block
        for block, at_end in _text_blocks(self.path, 0, None):
            data = left + block
            c = native.ascii_stl_chunk(data, at_end)
            if c["error"] is not None:
                raise self.fail(f"line {line + c['error'][0]}: {c['error'][1]}")
            base = len(parts)
            parts += [PartName(object=name) for _, name in c["statements"]]
            if len(c["corners"]):
                # A facet belongs to the last solid started before it.
                before = c["facet_statement"].astype(np.int64)
                part = np.where(before > 0, base + before - 1, current)
                if (part < 0).any():
                    parts.insert(0, PartName())  # facets before any solid
                    current, part = current + 1, np.where(part < 0, 0, part + 1)
                self._check(c["corners"], first)
                piece = TriangleChunk(first, len(part), corners=c["corners"], parts=part.astype(np.uint32))
                yield from _rechunk([piece], size)
                first += len(part)
            if c["statements"]:
                current = len(parts) - 1
            line += c["lines"]
            left = data[c["consumed"] :]
        if first == 0:
            raise self.fail("empty mesh (no facets)")
        self.parts = parts if len(parts) > 1 or any(p.object for p in parts) else None
        self.triangle_count, self.exact_count = first, True


def _rechunk(pieces: list[TriangleChunk], size: int) -> Iterator[TriangleChunk]:
    for piece in pieces:
        for start in range(0, piece.count, size):
            stop = min(piece.count, start + size)
            yield TriangleChunk(
                piece.first + start,
                stop - start,
                corners=piece.corners[start:stop],
                parts=None if piece.parts is None else piece.parts[start:stop],
            )


# ---- PLY ---------------------------------------------------------------------------------------


@dataclass
class _PlyElement:
    name: str
    count: int
    props: list[list[str]] = field(default_factory=list)

    def scalar(self, name: str) -> bool:
        return any(p[0] != "list" and p[1] == name for p in self.props)

    def list_name(self) -> str | None:
        names = [p[3] for p in self.props if p[0] == "list"]
        for want in ("vertex_indices", "vertex_index"):
            if want in names:
                return want
        return None

    def fixed_dtype(self, order: str) -> np.dtype | None:
        """The element's record dtype, or None when it has list properties."""
        if any(p[0] == "list" for p in self.props):
            return None
        return np.dtype([(p[1], order + _PLY_TYPES[p[0]]) for p in self.props])

    def describe(self, keep: Callable[[list[str]], bool]) -> list[tuple[list[str], bool]]:
        return [((["list", p[1], p[2]] if p[0] == "list" else [p[0]]), keep(p)) for p in self.props]


class PlySource(TriangleSource):
    """PLY: ASCII or binary of either byte order. Vertices need x, y, z; per-vertex and
    per-face red/green/blue (uchar, or float 0-1) are kept. Faces ('face' with
    vertex_indices or vertex_index, any polygon size, fans in file order) and triangle
    strips ('tristrips' with -1 restarts) give the triangles, in element order; other
    elements are skipped.

    A binary file's vertex element is read where it lies; its faces are read straight
    from the file, as fixed-size triangle records while every face is a triangle and
    parsed row by row from the first that is not. An ASCII file (or a binary one whose
    vertices cannot be located without parsing) is scanned once into staged arrays."""

    def __init__(
        self, path: str | os.PathLike[str], stage_dir: Path | None = None, progress: Progress | None = None
    ) -> None:
        super().__init__(path)
        self._read_header()
        self._faces = [e for e in self.elements if e.name in ("face", "tristrips")]
        vertex = next((e for e in self.elements if e.name == "vertex"), None)
        if vertex is None or not self._faces:
            raise self.fail("PLY needs vertex and face (or tristrips) elements")
        if not all(vertex.scalar(a) for a in "xyz"):
            raise self.fail("vertex element lacks x, y, z")
        for e in self._faces:
            if e.list_name() is None:
                raise self.fail(f"element {e.name!r} has no vertex_indices list")
        self._vertex = vertex
        self._vertex_colour = self._colour_props(vertex)
        self._face_colour = {e.name: self._colour_props(e) for e in self._faces}
        self._part_prop = {e.name: self._part_property(e) for e in self._faces}
        self._part_index: dict[int | None, int] = {}  # a part property's value (None: none) -> its part
        if any(self._part_prop.values()):
            self.parts = []
        self.has_colours = self._vertex_colour is not None or any(
            c is not None for c in self._face_colour.values()
        )
        self.triangle_count = sum(e.count for e in self._faces)
        self.exact_count = False
        offsets = self._element_offsets()
        if self.format != "ascii":
            least = self.data_offset + sum(e.count * self._least_row_bytes(e) for e in self.elements)
            size = self.path.stat().st_size
            if size < least:
                raise self.fail(f"truncated: {size} bytes, the header describes at least {least}")
        self._stage: _Stage | None = None
        if (
            self.format != "ascii"
            and vertex.fixed_dtype(self.order) is not None
            and offsets.get("vertex") is not None
        ):
            self._in_place(vertex, offsets)
        else:
            self._scan(stage_dir, progress)

    # -- header ----------------------------------------------------------------------------------

    def _read_header(self) -> None:
        with open(self.path, "rb") as f:
            header = b""
            while not header.endswith(b"end_header\n"):
                line = f.readline()
                if not line or len(header) > 1 << 16:
                    raise self.fail("cannot parse as PLY: no end_header")
                header += line.replace(b"\r\n", b"\n")
            self.data_offset = f.tell()
        lines = header.decode("ascii", errors="replace").splitlines()
        if not lines or lines[0].strip() != "ply":
            raise self.fail("cannot parse as PLY: not a PLY file")
        self.elements: list[_PlyElement] = []
        self.format = ""
        for line in lines[1:]:
            words = line.split()
            if not words or words[0] in ("comment", "obj_info", "end_header"):
                continue
            if words[0] == "format" and len(words) >= 2:
                if words[1] not in ("ascii", "binary_little_endian", "binary_big_endian"):
                    raise self.fail(f"unknown PLY format {words[1]!r}")
                self.format = words[1]
            elif words[0] == "element" and len(words) == 3:
                try:
                    self.elements.append(_PlyElement(words[1], int(words[2])))
                except ValueError:
                    raise self.fail(f"bad element line {line!r}") from None
            elif words[0] == "property" and self.elements:
                prop = words[1:]
                types = prop[1:3] if prop and prop[0] == "list" else prop[:1]
                if len(prop) < (4 if prop and prop[0] == "list" else 2) or any(
                    t not in _PLY_TYPES for t in types
                ):
                    raise self.fail(f"unknown PLY property {' '.join(prop)!r}")
                self.elements[-1].props.append(prop)
            else:
                raise self.fail(f"cannot parse as PLY: unexpected header line {line!r}")
        if not self.format:
            raise self.fail("cannot parse as PLY: no format line")
        self.order = ">" if self.format == "binary_big_endian" else "<"

    def _colour_props(self, e: _PlyElement) -> tuple[list[str], bool] | None:
        """(three property names, stored as floats 0-1) of an element's colour, or None."""
        for names in (["red", "green", "blue"], ["diffuse_red", "diffuse_green", "diffuse_blue"]):
            props = [next((p for p in e.props if p[0] != "list" and p[1] == n), None) for n in names]
            if all(p is not None for p in props):
                return names, any(p[0] in ("float", "float32", "double", "float64") for p in props if p)
        return None

    @staticmethod
    def _part_property(e: _PlyElement) -> str | None:
        """The integer face property that gives each face's part, or None."""
        for name in PLY_PART_PROPERTIES:
            prop = next((p for p in e.props if p[0] != "list" and p[1] == name), None)
            if prop is not None and np.dtype(_PLY_TYPES[prop[0]]).kind in "iu":
                return name
        return None

    def _parts_of(self, values: np.ndarray) -> np.ndarray:
        """Part indices (uint32) of part-property values, new values getting the next
        index in order of first use."""
        values = np.asarray(values).astype(np.int64)
        if len(values) == 0:
            return np.zeros(0, np.uint32)
        unique, first, inverse = np.unique(values, return_index=True, return_inverse=True)
        assert self.parts is not None
        for k in np.argsort(first, kind="stable"):
            v = int(unique[k])
            if v not in self._part_index:
                self._part_index[v] = len(self.parts)
                self.parts.append(PartName(object=f"part {v}"))
        lut = np.array([self._part_index[int(v)] for v in unique], dtype=np.uint32)
        return lut[inverse.reshape(-1)]

    def _unnamed(self, count: int) -> np.ndarray | None:
        """Parts of faces of an element without the part property (in a file where
        another has it): one unnamed part. None when the file has no part property."""
        if self.parts is None:
            return None
        index = self._part_index.get(None)
        if index is None:
            index = self._part_index[None] = len(self.parts)
            self.parts.append(PartName())
        return np.full(count, index, np.uint32)

    def _row_parts(self, e: _PlyElement, rows: dict[str, Any], row: np.ndarray) -> np.ndarray | None:
        """Per triangle (rows: each triangle's face row) its part, or None."""
        name = self._part_prop.get(e.name)
        if name is None:
            return self._unnamed(len(row))
        scalars = [p[1] for p in e.props if p[0] != "list"]
        values = rows["scalars"][:, scalars.index(name)]
        if len(values) and not np.isfinite(values).all():
            raise self.fail(f"{e.name} property {name!r} is not an integer")
        return self._parts_of(np.asarray(values)[row])

    def _least_row_bytes(self, e: _PlyElement) -> int:
        """The fewest bytes a binary row of `e` takes (a face lists at least three vertices)."""
        total = 0
        for p in e.props:
            if p[0] == "list":
                least = 3 if e.name == "face" and p[3] == e.list_name() else 0
                total += np.dtype(_PLY_TYPES[p[1]]).itemsize + least * np.dtype(_PLY_TYPES[p[2]]).itemsize
            else:
                total += np.dtype(_PLY_TYPES[p[0]]).itemsize
        return total

    def _element_offsets(self) -> dict[str, int | None]:
        """Byte offsets of the elements a binary file locates without parsing."""
        out: dict[str, int | None] = {}
        at: int | None = self.data_offset
        for e in self.elements:
            out[e.name] = at
            dtype = e.fixed_dtype(self.order)
            at = (
                None
                if (at is None or dtype is None or self.format == "ascii")
                else at + e.count * dtype.itemsize
            )
        return out

    # -- binary, vertices in place -------------------------------------------------------------

    def _in_place(self, vertex: _PlyElement, offsets: dict[str, int | None]) -> None:
        dtype = vertex.fixed_dtype(self.order)
        assert dtype is not None
        start = offsets["vertex"]
        assert start is not None
        end = start + vertex.count * dtype.itemsize
        if self.path.stat().st_size < end:
            raise self.fail(f"truncated: {self.path.stat().st_size} bytes, the vertices end at {end}")
        fields = dtype.fields
        assert fields is not None
        colours = None
        if self._vertex_colour is not None:
            names, is_float = self._vertex_colour
            rec = np.memmap(self.path, dtype=dtype, mode="r", offset=start, shape=(vertex.count,))
            colours = np.stack([_to_u8(rec[n], is_float) for n in names], axis=1)
            del rec
        self.vertices = VertexTable(
            vertex.count,
            dtype.itemsize,
            (fields["x"][1], fields["y"][1], fields["z"][1]),
            (_f(fields["x"][0]), _f(fields["y"][0]), _f(fields["z"][0])),
            path=self.path,
            offset=start,
            colours=colours,
        )
        self._offsets = offsets

    # -- scan: stage vertices and triangles ---------------------------------------------------

    def _scan(self, stage_dir: Path | None, progress: Progress | None) -> None:
        stage = self._stage = _Stage(stage_dir, "ply")
        try:
            first = 0
            for e, rows, at_row in self._rows(progress):
                if e.name == "vertex":
                    self._stage_vertices(stage, e, rows, at_row)
                elif e in self._faces:
                    first += self._stage_faces(stage, e, rows, first)
        finally:
            stage.close()
        self.triangle_count, self.exact_count = first, True
        count = stage.lengths.get("xyz", 0)
        self.vertices = stage.vertex_table("xyz", count, "vrgb")

    def _rows(self, progress: Progress | None) -> Iterator[tuple[_PlyElement, dict[str, Any], int]]:
        """(element, parsed rows, index of the first) for every element, in file order."""
        blocks = (
            _text_blocks(self.path, self.data_offset, progress)
            if self.format == "ascii"
            else _binary_blocks(self.path, self.data_offset, progress)
        )
        stream = _RowStream(blocks, self.data_offset, self.fail)
        for e in self.elements:
            keep_list = e.list_name()
            props = e.describe(lambda p, keep_list=keep_list: p[0] != "list" or p[3] == keep_list)
            for rows, first in stream.rows(e.count, _ply_parser(props, self.format), e.name):
                yield e, rows, first

    def _stage_vertices(self, stage: _Stage, e: _PlyElement, rows: dict[str, Any], at_row: int) -> None:
        scalars = [p[1] for p in e.props if p[0] != "list"]
        values = rows["scalars"]
        xyz = values[:, [scalars.index(a) for a in "xyz"]]
        _check_vertices(xyz, at_row, self.fail)
        stage.append("xyz", np.ascontiguousarray(xyz, dtype="<f8"))
        if self._vertex_colour is not None:
            names, is_float = self._vertex_colour
            stage.append(
                "vrgb", np.stack([_to_u8(values[:, scalars.index(n)], is_float) for n in names], axis=1)
            )

    def _stage_faces(self, stage: _Stage, e: _PlyElement, rows: dict[str, Any], first: int) -> int:
        tris, row, face_colours = self._triangulate(e, rows)
        if len(tris) and (tris.min() < 0 or tris.max() > MAX_VERTICES):
            bad = int(np.argmax(((tris < 0) | (tris > MAX_VERTICES)).any(axis=1)))
            raise self.fail(
                f"triangle {first + bad} refers to vertex {int(tris[bad].min())}, which no file has"
            )
        stage.append("tri", tris.astype("<u4"))
        if self.parts is not None:
            part = self._row_parts(e, rows, row)
            assert part is not None
            stage.append("part", part)
        if self.has_colours:
            rgb = face_colours[row] if face_colours is not None else np.zeros((len(row), 3), np.uint8)
            flag = np.full(len(row), face_colours is not None, dtype=np.uint8)
            stage.append("rgb", np.concatenate([rgb, flag[:, None]], axis=1))
        return len(tris)

    def _triangulate(
        self, e: _PlyElement, rows: dict[str, Any]
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        """(triangles (k, 3) int64, their rows, per-row face colours or None)."""
        counts, values = rows["list_counts"], rows["list_values"]
        if e.name == "tristrips":
            # A restart is -1, which an unsigned index type writes as its largest value.
            kind = next(p[2] for p in e.props if p[0] == "list" and p[3] == e.list_name())
            if kind.startswith("u"):
                restart = values == np.iinfo(_PLY_TYPES[kind]).max
                values = values.astype(np.int64)
                values[restart] = -1
            tris, row, _ = native.triangulate("strip", counts, values)
        elif len(counts) and (counts == 3).all():
            tris, row = values.reshape(-1, 3), np.arange(len(counts), dtype=np.uint64)
        else:
            tris, row, bad = native.triangulate("fan", counts, values)
            if bad >= 0:
                raise self.fail(f"a face with {int(counts[bad])} vertices (a face needs at least three)")
        colours = None
        if self._face_colour.get(e.name) is not None:
            names, is_float = self._face_colour[e.name]  # type: ignore[misc]
            scalars = [p[1] for p in e.props if p[0] != "list"]
            colours = np.stack(
                [_to_u8(rows["scalars"][:, scalars.index(n)], is_float) for n in names], axis=1
            )
        return tris, row.astype(np.int64), colours

    # -- chunks -----------------------------------------------------------------------------------

    def chunks(self, size: int = DEFAULT_CHUNK) -> Iterator[TriangleChunk]:
        assert self.vertices is not None
        if self._stage is not None:
            yield from self._staged_chunks(size)
            return
        first = 0
        at = self.data_offset  # elements in file order: each starts where the last ended
        for e in self.elements:
            dtype = e.fixed_dtype(self.order)
            if e in self._faces:
                end = [at]
                for chunk in self._binary_face_chunks(e, at, first, size, end):
                    yield chunk
                    first += chunk.count
                at = end[0]
            elif dtype is not None:
                at += e.count * dtype.itemsize
            else:
                at = self._skip_rows(e, at)
        self.triangle_count, self.exact_count = first, True

    def _skip_rows(self, e: _PlyElement, start: int) -> int:
        """The offset where element `e` (with list properties) ends."""
        stream = _RowStream(_binary_blocks(self.path, start, None), start, self.fail)
        for _ in stream.rows(e.count, _ply_parser(e.describe(lambda p: False), self.format), e.name):
            pass
        return stream.position

    def _staged_chunks(self, size: int) -> Iterator[TriangleChunk]:
        assert self._stage is not None
        yield from _staged_chunks(self._stage, self, size)

    def _colours(self, indices: np.ndarray, face_rgb_flag: np.ndarray | None) -> np.ndarray:
        assert self.vertices is not None
        return _triangle_colours(self.vertices, indices, face_rgb_flag)

    def _binary_face_chunks(
        self, e: _PlyElement, start: int, first: int, size: int, end: list[int]
    ) -> Iterator[TriangleChunk]:
        """Faces read in place: fixed-size triangle records while every face is a
        triangle, then parsed row by row. Sets end[0] to the offset past the element."""
        assert self.vertices is not None
        keep_list = e.list_name()
        fixed: list[tuple[str, str] | tuple[str, str, tuple[int]]] = []
        for p in e.props:
            if p[0] == "list":
                if p[3] == keep_list:
                    fixed += [
                        ("n", self.order + _PLY_TYPES[p[1]]),
                        ("v", self.order + _PLY_TYPES[p[2]], (3,)),
                    ]
                else:
                    fixed = []
                    break
            else:
                fixed.append((p[1], self.order + _PLY_TYPES[p[0]]))
        dtype = np.dtype(fixed) if fixed and e.name == "face" else None
        face_colour = self._face_colour.get(e.name)
        done = 0
        with open(self.path, "rb") as f:
            f.seek(start)
            while dtype is not None and done < e.count:
                block = np.fromfile(f, dtype=dtype, count=min(size, e.count - done))
                if len(block) < min(size, e.count - done):
                    raise self.fail(f"truncated: the file ends at {e.name} {done + len(block)} of {e.count}")
                triangle = block["n"] == 3
                k = len(block) if triangle.all() else int(np.argmin(triangle))
                if k:
                    tris = block["v"][:k]  # a view: the native gather reads any integer layout
                    colours = None
                    if self.has_colours:
                        rgb = None
                        if face_colour is not None:
                            names, is_float = face_colour
                            rgb = np.empty((k, 4), np.uint8)
                            for c, n in enumerate(names):
                                rgb[:, c] = _to_u8(block[n][:k], is_float)
                            rgb[:, 3] = 1
                        colours = self._colours(tris, rgb)
                    name = self._part_prop.get(e.name)
                    parts = self._parts_of(block[name][:k]) if name is not None else self._unnamed(k)
                    yield TriangleChunk(
                        first, k, indices=tris, vertices=self.vertices, colours=colours, parts=parts
                    )
                    first += k
                    done += k
                if k < len(block):
                    # A face that is not a triangle: parse row by row from it on.
                    start += (done) * dtype.itemsize
                    dtype = None
        if done == e.count:
            end[0] = start + (done * dtype.itemsize if dtype is not None else 0)
            return
        stream = _RowStream(_binary_blocks(self.path, start, None), start, self.fail)
        parse = _ply_parser(e.describe(lambda p: p[0] != "list" or p[3] == keep_list), self.format)
        remaining = e.count - done

        def capped(data: memoryview, rows: int, at_end: bool) -> dict[str, Any]:
            return parse(data, min(size, rows), at_end)

        for rows, _ in stream.rows(remaining, capped, e.name):
            tris, row, face_colours = self._triangulate(e, rows)
            colours = None
            if self.has_colours:
                rgb = None
                if face_colours is not None:
                    rgb = np.concatenate([face_colours[row], np.ones((len(row), 1), np.uint8)], axis=1)
                colours = self._colours(tris, rgb)
            parts = self._row_parts(e, rows, row)
            for at_tri in range(0, len(tris), size):  # polygons give several triangles a row
                stop = min(len(tris), at_tri + size)
                part_colours = None if colours is None else colours[at_tri:stop]
                yield TriangleChunk(
                    first + at_tri, stop - at_tri, indices=tris[at_tri:stop], vertices=self.vertices,
                    colours=part_colours, parts=None if parts is None else parts[at_tri:stop],
                )  # fmt: skip
            first += len(tris)
        end[0] = stream.position


def _binary_blocks(path: Path, start: int, progress: Progress | None) -> Iterator[tuple[bytes, bool]]:
    total = path.stat().st_size
    with open(path, "rb") as f:
        f.seek(start)
        done = start
        while True:
            data = f.read(TEXT_BLOCK)
            done += len(data)
            if progress is not None:
                progress(done, total)
            yield data, done >= total
            if done >= total or not data:
                return


def _f(dtype: np.dtype) -> str:
    """'<f4'-style name of a vertex coordinate type (integers are promoted by the PLY path)."""
    if dtype.kind != "f":
        raise MeshError(f"vertex coordinates of type {dtype} are not supported (float or double)")
    return ("<" if dtype.byteorder in "<=|" else ">") + f"f{dtype.itemsize}"


def _to_u8(values: np.ndarray, is_float: bool) -> np.ndarray:
    if not is_float and np.asarray(values).dtype == np.uint8:
        return np.asarray(values)
    v = np.asarray(values, dtype=np.float64)
    if is_float:
        v = v * 255.0
    return np.clip(np.rint(v), 0, 255).astype(np.uint8)


# ---- OBJ ----------------------------------------------------------------------------------------


class ObjSource(TriangleSource):
    """Wavefront OBJ: `v x y z [r g b]` vertices (1-based, negative indices relative),
    `f` faces of any size (fans), `o`/`g`/`usemtl` parts, `mtllib` materials whose `Kd`
    colours a part unless a `map_Kd` texture replaces it. Scanned once into staged
    vertices and triangles."""

    def __init__(
        self, path: str | os.PathLike[str], stage_dir: Path | None = None, progress: Progress | None = None
    ) -> None:
        super().__init__(path)
        stage = self._stage = _Stage(stage_dir, "obj")
        parts: dict[PartName, int] = {}
        current = PartName()
        materials: dict[str, np.ndarray | None] = {}
        vertices = triangles = faces = line = 0
        vertex_colours = False
        try:
            for data, _ in _text_blocks(self.path, 0, progress):
                c = native.obj_chunk(data, vertices)
                if c["error"] is not None:
                    raise self.fail(f"line {line + c['error'][0]}: {c['error'][1]}")
                xyz = c["vertices"]
                _check_vertices(xyz, vertices, self.fail)
                # Parts: the (object, group, material) in force for each triangle; a
                # part gets its index when a triangle first uses it.
                state = [current]
                for keyword, text in c["statements"]:
                    if keyword == "mtllib":
                        for name in text.split():
                            materials.update(_read_mtl(self.path.parent / name))
                    else:
                        current = _next_part(current, keyword, text)
                    state.append(current)
                stage.append("xyz", xyz)
                if c["vertex_colours"] is not None:
                    if not vertex_colours and vertices:
                        stage.append("vrgbf", np.full((vertices, 3), np.nan, np.float32))
                    vertex_colours = True
                    stage.append("vrgbf", c["vertex_colours"])
                elif vertex_colours:
                    stage.append("vrgbf", np.full((len(xyz), 3), np.nan, np.float32))
                tris = c["triangles"]
                if len(tris):
                    used = np.unique(c["triangle_statement"])
                    index = np.zeros(len(state), dtype="<u4")
                    for k in used:  # in file order: np.unique sorts, and statements come in order
                        index[k] = parts.setdefault(state[k], len(parts))
                    stage.append("tri", tris.astype("<u4"))
                    stage.append("part", index[c["triangle_statement"]])
                vertices += len(xyz)
                triangles += len(tris)
                faces += c["faces"]
                line += c["lines"]
                if vertices > MAX_VERTICES:
                    raise self.fail(f"more than {MAX_VERTICES} vertices")
        finally:
            stage.close()
        if faces == 0:
            raise self.fail("empty mesh (no faces)")
        self.triangle_count = triangles
        self.parts = sorted(parts, key=parts.__getitem__)
        self._material_rgb = [materials.get(p.material) for p in self.parts]
        self.has_colours = vertex_colours or any(c is not None for c in self._material_rgb)
        self._vertex_count = vertices
        self.vertices = self._vertex_table(stage, vertices, vertex_colours)

    def _vertex_table(self, stage: _Stage, count: int, vertex_colours: bool) -> VertexTable:
        table = stage.vertex_table("xyz", count, None)
        if vertex_colours:
            # Float colours 0-1 as written; NaN where a vertex has none.
            rgbf = (
                stage.array("vrgbf", (3,))
                if stage.directory is None
                else np.memmap(stage.path("vrgbf"), dtype=np.float32, mode="r", shape=(count, 3))
            )
            table.colours = rgbf  # type: ignore[assignment]
        return table

    def chunks(self, size: int = DEFAULT_CHUNK) -> Iterator[TriangleChunk]:
        assert self.vertices is not None
        material = None
        if any(c is not None for c in self._material_rgb):
            material = np.array([c if c is not None else _WHITE for c in self._material_rgb], dtype=np.uint8)
            has_material = np.array([c is not None for c in self._material_rgb])
        first = 0
        for tris, part in self._stage.rows(["tri", "part"], size):
            assert tris is not None and part is not None
            indices = tris.astype(np.int64)
            colours = None
            if self.has_colours:
                colours = np.tile(_WHITE, (len(indices), 1))
                if material is not None:
                    colours = material[part]
                if self.vertices.colours is not None:
                    bad = (indices < 0) | (indices >= self.vertices.count)
                    if bad.any():
                        t = first + int(np.argmax(bad.any(axis=1)))
                        raise self.fail(
                            f"triangle {t} refers to a vertex outside 1 ... {self.vertices.count}"
                        )
                    vc = np.asarray(self.vertices.colours)[indices]  # float 0-1, NaN: none
                    known = ~np.isnan(vc).any(axis=(1, 2))
                    mean = np.clip(np.rint(vc[known].mean(axis=1) * 255.0), 0, 255).astype(np.uint8)
                    colours[known] = mean
                    if material is not None:
                        colours[~known & ~has_material[part]] = _WHITE
            yield TriangleChunk(
                first, len(tris), indices=indices, vertices=self.vertices, colours=colours, parts=part
            )
            first += len(tris)


def _next_part(current: PartName, keyword: str, text: str) -> PartName:
    if keyword == "o":
        return PartName(text, current.group, current.material)
    if keyword == "g":
        return PartName(current.object, text, current.material)
    return PartName(current.object, current.group, text)


def _read_mtl(path: Path) -> dict[str, np.ndarray | None]:
    """{material: its Kd colour as uint8, or None when textured or without Kd}."""
    out: dict[str, np.ndarray | None] = {}
    try:
        text = path.read_text(errors="replace")
    except OSError:
        return out  # a missing .mtl leaves the parts uncoloured, as viewers do
    name = None
    kd: dict[str, np.ndarray] = {}
    textured: set[str] = set()
    for line in text.splitlines():
        words = line.split()
        if not words:
            continue
        if words[0] == "newmtl" and len(words) > 1:
            name = " ".join(words[1:])
            out.setdefault(name, None)
        elif name is not None and words[0] == "Kd" and len(words) >= 4:
            try:
                kd[name] = np.clip(np.rint(np.array([float(w) for w in words[1:4]]) * 255.0), 0, 255).astype(
                    np.uint8
                )
            except ValueError:
                continue
        elif name is not None and words[0] == "map_Kd":
            textured.add(name)
    for m in out:
        out[m] = kd.get(m) if m not in textured else None
    return out


# ---- OFF ----------------------------------------------------------------------------------------


class OffSource(TriangleSource):
    """OFF / COFF (ASCII): a header line, the counts `V F E`, V vertex lines (x y z, and
    r g b [a] in COFF), F face lines (n i0 ... i(n-1) [r g b [a]]); polygons as fans.
    Scanned once into staged vertices and triangles."""

    def __init__(
        self, path: str | os.PathLike[str], stage_dir: Path | None = None, progress: Progress | None = None
    ) -> None:
        super().__init__(path)
        with open(self.path, "rb") as f:
            head = f.read(4096)
        tokens, body = _off_header(head)
        if tokens is None:
            raise self.fail("cannot parse as OFF: no OFF header with vertex and face counts")
        kind, n_vertices, n_faces = tokens
        if "N" in kind or "ST" in kind or "4" in kind or kind.startswith("n"):
            raise self.fail(f"OFF variant {kind!r} is not supported (OFF, COFF)")
        coloured_vertices = kind.startswith("C")
        stage = self._stage = _Stage(stage_dir, "off")
        props: list[tuple[list[str], bool]] = [(["double"], True)] * (7 if coloured_vertices else 3)
        stream = _RowStream(_text_blocks(self.path, body, progress), body, self.fail)
        triangles = 0
        face_colours = False
        try:
            for rows, done in stream.rows(n_vertices, _ply_parser(props, "ascii"), "vertex"):
                xyz = rows["scalars"][:, :3]
                _check_vertices(xyz, done, self.fail)
                stage.append("xyz", np.ascontiguousarray(xyz))
                if coloured_vertices:
                    c = rows["scalars"][:, 3:6]
                    stage.append("vrgb", _to_u8(c, bool((c != np.floor(c)).any() or c.max(initial=0) <= 1.0)))
            for rows, done in stream.rows(n_faces, native.off_faces, "face"):
                tris, row, bad = native.triangulate("fan", rows["list_counts"], rows["list_values"])
                if bad >= 0:
                    raise self.fail(f"face {done + bad}: a face needs at least three vertices")
                stage.append("tri", tris.astype("<u4"))
                c = rows["colours"][row.astype(np.int64), :3]
                has = ~np.isnan(c).any(axis=1)
                face_colours |= bool(has.any())
                scaled = bool((c[has] != np.floor(c[has])).any() or (has.any() and c[has].max() <= 1.0))
                rgb = np.zeros((len(row), 4), np.uint8)
                rgb[has, :3] = _to_u8(c[has], scaled)
                rgb[has, 3] = 1
                stage.append("rgb", rgb)
                triangles += len(tris)
        finally:
            stage.close()
        if n_faces == 0:
            raise self.fail("empty mesh (no faces)")
        self.triangle_count = triangles
        self.vertices = stage.vertex_table("xyz", n_vertices, "vrgb")
        self.has_colours = coloured_vertices or face_colours
        self._face_colours = face_colours

    def chunks(self, size: int = DEFAULT_CHUNK) -> Iterator[TriangleChunk]:
        yield from _staged_chunks(self._stage, self, size)


def _staged_chunks(stage: _Stage, source: TriangleSource, size: int) -> Iterator[TriangleChunk]:
    """The staged triangles ("tri") of a PLY or OFF file, coloured from the staged face
    colours ("rgb": r, g, b, flag) and the vertex colours."""
    table = source.vertices
    assert table is not None
    first = 0
    for tris, rgb, part in stage.rows(["tri", "rgb", "part"], size):
        assert tris is not None
        indices = tris.astype(np.int64)
        colours = _triangle_colours(table, indices, rgb) if source.has_colours else None
        yield TriangleChunk(first, len(tris), indices=indices, vertices=table, colours=colours, parts=part)
        first += len(tris)


def _off_header(head: bytes) -> tuple[tuple[str, int, int] | None, int]:
    """((kind, vertices, faces), byte offset of the first vertex line)."""
    pos = 0
    words: list[str] = []
    kind = ""
    while pos < len(head):
        end = head.find(b"\n", pos)
        if end < 0:
            break
        line = head[pos:end].split(b"#", 1)[0].decode("ascii", errors="replace").split()
        pos = end + 1
        if not line:
            continue
        if not kind:
            if not line[0].endswith("OFF"):
                return None, 0
            kind = line[0]
            line = line[1:]
        words += line
        if len(words) >= 3:
            try:
                return (kind, int(words[0]), int(words[1])), pos
            except ValueError:
                return None, 0
    return None, 0


# ---- glTF / GLB ---------------------------------------------------------------------------------

_GLTF_COMPONENTS = {5120: "i1", 5121: "u1", 5122: "<i2", 5123: "<u2", 5125: "<u4", 5126: "<f4"}
_GLTF_WIDTH = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4}


class GltfSource(TriangleSource):
    """glTF 2.0 (.gltf with external or data-URI buffers, or .glb): every mesh primitive
    of mode TRIANGLES, TRIANGLE_STRIP or TRIANGLE_FAN placed by the scene's nodes (their
    matrices or translation/rotation/scale, composed down the hierarchy, in double), in
    node order. A part per placed primitive, named by node, mesh and material. Buffers
    are mapped, not loaded."""

    def __init__(self, path: str | os.PathLike[str]) -> None:
        super().__init__(path)
        self._doc, self._bin_offset = self._load()
        doc = self._doc
        self._buffers: list[tuple[Path | None, int, bytes | None]] = []
        for i, b in enumerate(doc.get("buffers", [])):
            uri = b.get("uri")
            if uri is None:
                if self._bin_offset is None:
                    raise self.fail(f"buffer {i} has no uri and the file has no binary chunk")
                self._buffers.append((self.path, self._bin_offset, None))
            elif uri.startswith("data:"):
                try:
                    self._buffers.append((None, 0, base64.b64decode(uri.split(",", 1)[1])))
                except (ValueError, IndexError):
                    raise self.fail(f"buffer {i}: bad data URI") from None
            else:
                file = self.path.parent / _unquote(uri)
                if not file.is_file():
                    raise self.fail(f"buffer {i}: {file} not found")
                self._buffers.append((file, 0, None))
        self._instances = self._place()
        self.triangle_count = sum(count for *_, count in self._instances)
        names: dict[PartName, int] = {}
        self._instance_part = [names.setdefault(name, len(names)) for _, _, name, _ in self._instances]
        self.parts = sorted(names, key=names.__getitem__) or None
        self._material_rgb = [self._material_colour(prim) for _, prim, _, _ in self._instances]
        self.has_colours = any(c is not None for c in self._material_rgb) or any(
            "COLOR_0" in prim.get("attributes", {}) for _, prim, _, _ in self._instances
        )

    def _load(self) -> tuple[dict[str, Any], int | None]:
        with open(self.path, "rb") as f:
            magic = f.read(12)
            if magic[:4] == b"glTF":
                version = struct.unpack("<I", magic[4:8])[0]
                if version != 2:
                    raise self.fail(f"glTF version {version} is not supported (2)")
                head = f.read(8)
                if len(head) < 8:
                    raise self.fail("cannot parse as GLB: truncated")
                chunk_len, chunk_type = struct.unpack("<II", head)
                if chunk_type != 0x4E4F534A:
                    raise self.fail("cannot parse as GLB: the first chunk is not JSON")
                text = f.read(chunk_len)
                bin_offset = None
                head = f.read(8)
                if len(head) == 8:
                    if struct.unpack("<II", head)[1] == 0x004E4942:  # BIN
                        bin_offset = f.tell()
            else:
                text = magic + f.read()
                bin_offset = None
        try:
            doc = json.loads(text)
        except (ValueError, UnicodeDecodeError) as exc:
            raise self.fail(f"cannot parse as glTF: {exc}") from None
        if not isinstance(doc, dict) or not str(doc.get("asset", {}).get("version", "")).startswith("2"):
            raise self.fail("cannot parse as glTF: not a glTF 2.0 document")
        if doc.get("extensionsRequired"):
            raise self.fail(f"glTF extensions {', '.join(doc['extensionsRequired'])} are not supported")
        return doc, bin_offset

    def _place(self) -> list[tuple[np.ndarray, dict[str, Any], PartName, int]]:
        """(4x4 world transform, primitive, part name, triangles) per placed primitive."""
        doc = self._doc
        nodes = doc.get("nodes", [])
        scenes = doc.get("scenes", [])
        if scenes:
            roots = scenes[doc.get("scene", 0)].get("nodes", [])
        else:
            children = {c for n in nodes for c in n.get("children", [])}
            roots = [i for i in range(len(nodes)) if i not in children]
        out: list[tuple[np.ndarray, dict[str, Any], PartName, int]] = []

        def visit(i: int, parent: np.ndarray, depth: int) -> None:
            if depth > 256:
                raise self.fail("node hierarchy deeper than 256 (a cycle?)")
            node = nodes[i]
            world = parent @ _node_matrix(node)
            if "mesh" in node:
                mesh = doc["meshes"][node["mesh"]]
                for k, prim in enumerate(mesh.get("primitives", [])):
                    mode = prim.get("mode", 4)
                    if mode not in (4, 5, 6):
                        continue  # points and lines have no triangles
                    material = prim.get("material")
                    mname = (
                        doc["materials"][material].get("name", f"material {material}")
                        if material is not None
                        else ""
                    )
                    name = PartName(
                        node.get("name", f"node {i}"),
                        mesh.get("name", f"mesh {node['mesh']}") + f"/{k}",
                        mname,
                    )
                    out.append((world, prim, name, self._triangles(prim)))
            for c in node.get("children", []):
                visit(c, world, depth + 1)

        for r in roots:
            visit(r, np.eye(4), 0)
        return out

    def _accessor(self, index: int) -> tuple[np.ndarray, int]:
        """An accessor as an array (mapped where it lies in a file), and its width."""
        doc = self._doc
        acc = doc["accessors"][index]
        if "sparse" in acc:
            raise self.fail(f"accessor {index}: sparse accessors are not supported")
        dtype = np.dtype(_GLTF_COMPONENTS[acc["componentType"]])
        width = _GLTF_WIDTH.get(acc["type"], 0)
        if not width:
            raise self.fail(f"accessor {index}: type {acc['type']} is not a vector")
        count = acc["count"]
        if "bufferView" not in acc:
            return np.zeros((count, width), dtype), width
        view = doc["bufferViews"][acc["bufferView"]]
        path, base, data = self._buffers[view["buffer"]]
        start = base + view.get("byteOffset", 0) + acc.get("byteOffset", 0)
        stride = view.get("byteStride") or dtype.itemsize * width
        length = (count - 1) * stride + dtype.itemsize * width if count else 0
        if count == 0:
            return np.zeros((0, width), dtype), width
        if data is not None:
            if start + length > len(data):
                raise self.fail(f"accessor {index} runs past the end of its buffer")
            raw: np.ndarray = np.frombuffer(data, dtype=np.uint8, count=length, offset=start)
        else:
            assert path is not None
            if start + length > path.stat().st_size:
                raise self.fail(f"accessor {index} runs past the end of its buffer")
            raw = np.memmap(path, dtype=np.uint8, mode="r", offset=start, shape=(length,))
        arr = np.ndarray((count, width), dtype=dtype, buffer=raw, offset=0, strides=(stride, dtype.itemsize))
        if acc.get("normalized"):
            info = np.iinfo(dtype)
            arr = np.maximum(arr.astype(np.float64) / info.max, -1.0)
        return arr, width

    def _triangles(self, prim: dict[str, Any]) -> int:
        n = (
            self._doc["accessors"][prim["indices"]]["count"]
            if "indices" in prim
            else self._doc["accessors"][prim["attributes"]["POSITION"]]["count"]
        )
        return n // 3 if prim.get("mode", 4) == 4 else max(0, n - 2)

    def _material_colour(self, prim: dict[str, Any]) -> np.ndarray | None:
        m = prim.get("material")
        if m is None:
            return None
        pbr = self._doc["materials"][m].get("pbrMetallicRoughness", {})
        if "baseColorTexture" in pbr or "baseColorFactor" not in pbr:
            return None
        return np.clip(
            np.rint(np.asarray(pbr["baseColorFactor"][:3], dtype=np.float64) * 255.0), 0, 255
        ).astype(np.uint8)

    def vertex_bounds(self) -> tuple[np.ndarray, np.ndarray] | None:
        lo, hi = np.full(3, np.inf), np.full(3, -np.inf)
        for world, prim, _, count in self._instances:
            if count == 0:
                continue
            pos, _ = self._accessor(prim["attributes"]["POSITION"])
            for start in range(0, len(pos), DEFAULT_CHUNK):
                p = np.asarray(pos[start : start + DEFAULT_CHUNK, :3], dtype=np.float64)
                if not np.isfinite(p).all():
                    raise self.fail("a vertex has a non-finite coordinate")
                w = p @ world[:3, :3].T + world[:3, 3]
                lo, hi = np.minimum(lo, w.min(axis=0)), np.maximum(hi, w.max(axis=0))
        return (lo, hi) if np.isfinite(lo).all() else None

    def chunks(self, size: int = DEFAULT_CHUNK) -> Iterator[TriangleChunk]:
        first = 0
        for (world, prim, _, count), part, colour in zip(
            self._instances, self._instance_part, self._material_rgb, strict=True
        ):
            if count == 0:
                continue
            pos, _ = self._accessor(prim["attributes"]["POSITION"])
            if "indices" in prim:
                idx, _ = self._accessor(prim["indices"])
                idx = idx.reshape(-1)
            else:
                idx = None
            vcol = None
            if "COLOR_0" in prim["attributes"]:
                vcol, _ = self._accessor(prim["attributes"]["COLOR_0"])
            mode = prim.get("mode", 4)
            for start in range(0, count, size):
                stop = min(count, start + size)
                t = np.arange(start, stop, dtype=np.int64)
                if mode == 4:
                    corner = (3 * t)[:, None] + np.arange(3)
                elif mode == 5:  # strip: odd triangles swap their first two corners
                    odd = (t % 2)[:, None]
                    corner = t[:, None] + np.where(odd, [1, 0, 2], [0, 1, 2])
                else:  # fan around the first vertex
                    corner = np.stack([np.zeros_like(t), t + 1, t + 2], axis=1)
                vi = np.asarray(idx[corner], dtype=np.int64) if idx is not None else corner
                if (vi < 0).any() or (vi >= len(pos)).any():
                    raise self.fail(f"triangle {first + start} refers to a vertex outside its primitive")
                p = np.asarray(pos[:, :3][vi], dtype=np.float64)
                corners = p @ world[:3, :3].T + world[:3, 3]
                self._check(corners, first + start)
                colours = None
                if self.has_colours:
                    if vcol is not None:  # floats 0-1 (normalized integers were scaled on reading)
                        c = np.asarray(vcol[:, :3], dtype=np.float64)[vi].mean(axis=1)
                        colours = np.clip(np.rint(c * 255.0), 0, 255).astype(np.uint8)
                    else:
                        colours = np.tile(colour if colour is not None else _WHITE, (stop - start, 1))
                parts = np.full(stop - start, part, dtype=np.uint32)
                yield TriangleChunk(
                    first + start, stop - start, corners=corners, colours=colours, parts=parts
                )
            first += count


def _node_matrix(node: dict[str, Any]) -> np.ndarray:
    if "matrix" in node:
        return np.asarray(node["matrix"], dtype=np.float64).reshape(4, 4).T  # column-major
    t = np.asarray(node.get("translation", [0, 0, 0]), dtype=np.float64)
    x, y, z, w = np.asarray(node.get("rotation", [0, 0, 0, 1]), dtype=np.float64)
    s = np.asarray(node.get("scale", [1, 1, 1]), dtype=np.float64)
    r = np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )
    m = np.eye(4)
    m[:3, :3] = r * s
    m[:3, 3] = t
    return m


def _unquote(uri: str) -> str:
    from urllib.parse import unquote

    return unquote(uri)


# ---- opening ------------------------------------------------------------------------------------

# Maps a file extension to the format it is read as.
STREAMED_EXTENSIONS: dict[str, str] = {
    ".obj": "obj", ".ply": "ply", ".stl": "stl", ".off": "off", ".gltf": "gltf", ".glb": "glb",
    ".f32": "soup", ".soup": "soup",
}  # fmt: skip


def open_triangles(
    path: str | os.PathLike[str], stage_dir: Path | None = None, progress: Progress | None = None
) -> TriangleSource:
    """Open any supported mesh file for streaming. Text formats are scanned here (their
    vertices and triangles staged in `stage_dir`, or in memory without one; `progress`
    hears the bytes scanned). Raises MeshError naming the file and the problem."""
    p = Path(path)
    if not p.is_file():
        raise MeshError(f"{p}: no such file")
    ext = p.suffix.lower()
    if ext == ".ply":
        return PlySource(p, stage_dir, progress)
    if ext == ".stl":
        return _open_stl(p)
    if ext == ".obj":
        return ObjSource(p, stage_dir, progress)
    if ext == ".off":
        return OffSource(p, stage_dir, progress)
    if ext in (".gltf", ".glb"):
        return GltfSource(p)
    if ext in (".f32", ".soup"):
        return RawSoupSource(p)
    supported = ", ".join(STREAMED_EXTENSIONS)
    raise MeshError(f"{p}: unsupported file extension {ext!r} (supported: {supported})")


def _open_stl(p: Path) -> TriangleSource:
    size = p.stat().st_size
    with open(p, "rb") as f:
        head = f.read(84)
    binary_size = 84 + 50 * int.from_bytes(head[80:84], "little") if len(head) >= 84 else -1
    if head[:5].lower() == b"solid" and size != binary_size:
        return AsciiStlSource(p)
    return StlSource(p)
