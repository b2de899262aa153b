"""The built-model file: header, block index and checksummed LZ4 blocks (docs/FORMAT.md).

`ModelFile` opens a model, verifies its header and index, reads and verifies any
block, reports statistics per LOD level, and decodes the whole model into an in-core
scene for full-detail renders. The block contents (treelets, voxels, triangle blocks)
are produced and walked by the native core; their bit layouts are in
native/include/vastray/format.h.
"""

from __future__ import annotations

import os
import struct
import zlib
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, BinaryIO

from vastray import native

# The format's constants have one home, native/include/vastray/format.h.
_F = native.FORMAT
MAGIC: bytes = _F["magic"]  # ends in \x1a, which stops `type`/`cat` from dumping binary
VERSION: int = _F["version"]
HEADER_SIZE: int = _F["header_size"]
BLOCK_SIZE: int = _F["block_size"]
CODEC_STORED: int = _F["codec_stored"]  # raw bytes (compression would not have saved space)
CODEC_LZ4: int = _F["codec_lz4"]  # LZ4 block format, no frame
CODEC_FAMILY_LZ4: int = _F["codec_family_lz4"]
FLAG_COLOURS: int = _F["flag_colours"]
FLAG_TRIANGLE_IDS: int = _F["flag_triangle_ids"]
FLAG_PART_IDS: int = _F["flag_part_ids"]  # reserved: no input reader keeps part ids yet

# Header fields in file order; the struct format is derived from this table so the two
# cannot drift apart. (name, struct code)
_HEADER_FIELDS: tuple[tuple[str, str], ...] = (
    ("magic", "8s"),
    ("version", "I"),
    ("header_size", "I"),
    ("flags", "I"),
    ("block_size", "I"),
    ("codec", "I"),
    ("level_count", "I"),
    ("centre", "3d"),
    ("cell_lo", "3f"),
    ("cell_hi", "3f"),
    ("triangle_count", "Q"),
    ("input_triangles", "Q"),
    ("degenerate", "Q"),
    ("basic_nodes", "Q"),
    ("lod_nodes", "Q"),
    ("leaves", "Q"),
    ("voxels_one", "Q"),
    ("voxels_six", "Q"),
    ("references", "Q"),
    ("block_count", "Q"),
    ("index_offset", "Q"),
    ("data_offset", "Q"),
    ("raw_bytes", "Q"),
    ("file_size", "Q"),
    ("index_crc32", "I"),
    ("header_crc32", "I"),
)
_HEADER_STRUCT = struct.Struct("<" + "".join(code for _, code in _HEADER_FIELDS))
_HEADER_CRC_AT = _HEADER_STRUCT.size - 4
assert _HEADER_STRUCT.size <= HEADER_SIZE and _HEADER_CRC_AT == _F["header_crc_at"]
# first block, block count, then what the level holds: node levels count their nodes
# and LOD voxels, the triangle level its triangle records and vertices.
_LEVEL = struct.Struct("<IIQQ")
_ENTRY = struct.Struct("<QIIII")  # offset, stored size, raw size, crc32 of stored bytes, codec
assert _LEVEL.size == _F["level_record"] and _ENTRY.size == _F["entry_record"]


class ModelError(ValueError):
    """A model file that is not a model, is damaged, or has an unsupported version."""


@dataclass
class BlockEntry:
    offset: int
    stored_size: int
    raw_size: int
    crc32: int
    codec: int


def _pack_header(fields: dict[str, Any]) -> bytes:
    values: list[Any] = []
    for name, code in _HEADER_FIELDS:
        v = fields[name]
        values.extend(v if code.startswith("3") else [v])
    packed = bytearray(_HEADER_STRUCT.pack(*values).ljust(HEADER_SIZE, b"\0"))
    crc = zlib.crc32(bytes(packed[:_HEADER_CRC_AT]) + bytes(4) + bytes(packed[_HEADER_CRC_AT + 4 :]))
    struct.pack_into("<I", packed, _HEADER_CRC_AT, crc)
    return bytes(packed)


def _unpack_header(data: bytes) -> dict[str, Any]:
    values = list(_HEADER_STRUCT.unpack_from(data))
    fields: dict[str, Any] = {}
    for name, code in _HEADER_FIELDS:
        if code.startswith("3"):
            fields[name], values = tuple(values[:3]), values[3:]
        else:
            fields[name], values = values[0], values[1:]
    return fields


def write_model_file(
    out: BinaryIO,
    fields: dict[str, Any],
    levels: list[tuple[int, int, int, int]],
    entries: list[tuple[int, int, int, int]],
    block_data: Iterator[bytes],
) -> int:
    """Writes header, index and blocks. `entries` are (stored size, raw size, crc, codec)
    in block order; `block_data` yields the stored bytes in the same order (it may yield
    them in larger runs). Returns the file size."""
    index_size = _LEVEL.size * len(levels) + _ENTRY.size * len(entries)
    data_offset = HEADER_SIZE + index_size
    index = bytearray()
    for first, count, items, extra in levels:
        index += _LEVEL.pack(first, count, items, extra)
    offset = data_offset
    for stored, raw, crc, codec in entries:
        index += _ENTRY.pack(offset, stored, raw, crc, codec)
        offset += stored
    header = dict(fields)
    header.update(
        magic=MAGIC,
        version=VERSION,
        header_size=HEADER_SIZE,
        block_size=BLOCK_SIZE,
        codec=CODEC_FAMILY_LZ4,
        level_count=len(levels),
        block_count=len(entries),
        index_offset=HEADER_SIZE,
        data_offset=data_offset,
        raw_bytes=sum(e[1] for e in entries),
        file_size=offset,
        index_crc32=zlib.crc32(index),
        header_crc32=0,
    )
    out.write(_pack_header(header))
    out.write(index)
    written = data_offset
    for chunk in block_data:
        out.write(chunk)
        written += len(chunk)
    if written != offset:
        raise RuntimeError(f"wrote {written} bytes but the index describes {offset}")
    return offset


class ModelFile:
    """An opened, verified model. Block reads check size and checksum before decoding."""

    def __init__(self, path: str | os.PathLike[str]) -> None:
        self.path = Path(path)
        self._file = open(self.path, "rb")
        try:
            self._open()
        except BaseException:
            self._file.close()
            raise

    def _fail(self, what: str) -> ModelError:
        return ModelError(f"{self.path}: {what}")

    def _open(self) -> None:
        size = os.fstat(self._file.fileno()).st_size
        head = self._file.read(HEADER_SIZE)
        if len(head) < 8 or head[:8] != MAGIC:
            raise self._fail("not a vastray model (bad magic bytes)")
        if len(head) < HEADER_SIZE:
            raise self._fail(f"truncated: {size} bytes, shorter than the {HEADER_SIZE}-byte header")
        h = _unpack_header(head)
        if h["version"] != VERSION:
            raise self._fail(
                f"format version {h['version']} is not supported (this vastray reads version {VERSION}); "
                "rebuild the model with this version"
            )
        crc = zlib.crc32(head[:_HEADER_CRC_AT] + bytes(4) + head[_HEADER_CRC_AT + 4 :])
        if crc != h["header_crc32"]:
            raise self._fail("header checksum mismatch (the header is corrupted)")
        if h["file_size"] != size:
            raise self._fail(
                f"file is {size} bytes but its header says {h['file_size']} (truncated or appended to)"
            )
        if h["block_size"] != BLOCK_SIZE or h["header_size"] != HEADER_SIZE:
            raise self._fail("unsupported block or header size")
        if h["codec"] != CODEC_FAMILY_LZ4:
            raise self._fail(f"unsupported block codec family {h['codec']}")
        if not h["flags"] & FLAG_TRIANGLE_IDS or h["flags"] & ~(FLAG_COLOURS | FLAG_TRIANGLE_IDS):
            raise self._fail(f"unsupported attribute flags {h['flags']:#x}")
        self.header = h
        index_size = _LEVEL.size * h["level_count"] + _ENTRY.size * h["block_count"]
        if h["index_offset"] + index_size != h["data_offset"] or h["data_offset"] > size:
            raise self._fail("index does not fit the file")
        self._file.seek(h["index_offset"])
        index = self._file.read(index_size)
        if zlib.crc32(index) != h["index_crc32"]:
            raise self._fail("block index checksum mismatch (the index is corrupted)")
        table = [_LEVEL.unpack_from(index, _LEVEL.size * i) for i in range(h["level_count"])]
        self.levels = [(first, count) for first, count, _, _ in table]
        # Per level: (nodes, LOD voxels) for node levels, (triangle records, vertices) for the last.
        self.level_contents = [(items, extra) for _, _, items, extra in table]
        base = _LEVEL.size * h["level_count"]
        self.blocks = [
            BlockEntry(*_ENTRY.unpack_from(index, base + _ENTRY.size * i)) for i in range(h["block_count"])
        ]
        expected = 0
        for first, count in self.levels:
            if first != expected:
                raise self._fail("levels do not tile the block index")
            expected += count
        if expected != len(self.blocks):
            raise self._fail("levels do not cover every block")
        for i, e in enumerate(self.blocks):
            if e.offset < h["data_offset"] or e.offset + e.stored_size > size or e.raw_size > BLOCK_SIZE:
                raise self._fail(f"block {i} lies outside the file or is oversized")

    # -- properties ----------------------------------------------------------------------

    @property
    def has_colours(self) -> bool:
        return bool(self.header["flags"] & FLAG_COLOURS)

    @property
    def node_levels(self) -> int:
        return len(self.levels) - 1

    @property
    def bounds(self) -> tuple[list[float], list[float]]:
        c = self.header["centre"]
        lo = [c[i] + self.header["cell_lo"][i] for i in range(3)]
        hi = [c[i] + self.header["cell_hi"][i] for i in range(3)]
        return lo, hi

    def level_of(self, block: int) -> int:
        for level, (first, count) in enumerate(self.levels):
            if first <= block < first + count:
                return level
        raise IndexError(f"block {block} out of range (model has {len(self.blocks)})")

    def level_name(self, block: int) -> str:
        """The numbering `vastray inspect` prints: LOD levels 0.., then the triangle level."""
        level = self.level_of(block)
        return "triangle level" if level == len(self.levels) - 1 else f"LOD level {level}"

    # -- block access --------------------------------------------------------------------

    def read_block(self, block: int) -> bytes:
        """The raw (decompressed) bytes of one block, verified."""
        if not 0 <= block < len(self.blocks):
            raise IndexError(f"block {block} out of range (model has {len(self.blocks)})")
        e = self.blocks[block]
        self._file.seek(e.offset)
        stored = self._file.read(e.stored_size)
        if len(stored) != e.stored_size:
            raise self._fail(f"block {block} is truncated")
        if zlib.crc32(stored) != e.crc32:
            raise self._fail(
                f"block {block} ({self.level_name(block)}) checksum mismatch: the file is corrupted"
            )
        if e.codec == CODEC_STORED:
            if e.raw_size != e.stored_size:
                raise self._fail(f"block {block}: stored block with a different raw size")
            return stored
        if e.codec != CODEC_LZ4:
            raise self._fail(f"block {block}: unknown codec {e.codec}")
        try:
            return native.lz4_decompress(stored, e.raw_size)
        except ValueError as exc:
            raise self._fail(f"block {block}: {exc}") from None

    def verify(self, progress: Callable[[int], None] | None = None) -> None:
        """Reads and checks every block (checksum, decompression, size)."""
        for i in range(len(self.blocks)):
            self.read_block(i)
            if progress is not None:
                progress(1)

    def to_scene(self) -> native.Scene:
        """Decodes every block into an in-core scene (full detail, every triangle)."""
        raw = [self.read_block(i) for i in range(len(self.blocks))]
        try:
            return native.decode_model(
                raw,
                [first for first, _ in self.levels],
                list(self.header["centre"]),
                list(self.header["cell_lo"]),
                list(self.header["cell_hi"]),
                self.header["input_triangles"],
                self.has_colours,
            )
        except RuntimeError as exc:
            raise self._fail(str(exc)) from None

    def stats(self) -> dict[str, Any]:
        h = self.header
        levels = []
        for level, (first, count) in enumerate(self.levels):
            entries = self.blocks[first : first + count]
            items, extra = self.level_contents[level]
            row: dict[str, Any] = {
                "level": level if level < self.node_levels else "triangles",
                "blocks": count,
            }
            if level < self.node_levels:
                row.update(nodes=items, voxels=extra)
            else:
                row.update(triangle_records=items, vertices=extra)
            row.update(
                raw_bytes=sum(e.raw_size for e in entries), stored_bytes=sum(e.stored_size for e in entries)
            )
            levels.append(row)
        stored = sum(e.stored_size for e in self.blocks)
        return {
            "path": str(self.path),
            "version": h["version"],
            "file_bytes": h["file_size"],
            "triangles": h["triangle_count"],
            "input_triangles": h["input_triangles"],
            "degenerate": h["degenerate"],
            "colours": self.has_colours,
            "bounds": self.bounds,
            "centre": list(h["centre"]),
            "nodes": h["basic_nodes"] + h["lod_nodes"] + h["leaves"],
            "basic_nodes": h["basic_nodes"],
            "lod_nodes": h["lod_nodes"],
            "leaves": h["leaves"],
            "voxels": h["voxels_one"] + h["voxels_six"],
            "voxels_one": h["voxels_one"],
            "voxels_six": h["voxels_six"],
            "references": h["references"],
            "blocks": len(self.blocks),
            "raw_bytes": h["raw_bytes"],
            "stored_bytes": stored,
            "compression_ratio": h["raw_bytes"] / stored if stored else 1.0,
            "bytes_per_triangle": h["file_size"] / max(1, h["triangle_count"]),
            "levels": levels,
        }

    def close(self) -> None:
        self._file.close()

    def __enter__(self) -> ModelFile:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
