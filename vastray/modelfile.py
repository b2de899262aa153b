"""The built-model file: header, block index, checksummed LZ4 blocks and, when the input
named parts, a parts section (docs/FORMAT.md).

`ModelFile` opens a model, verifies its header, index and parts section, reads and
verifies any block, reports statistics per LOD level and per coarseness tier, tells the
part of any input triangle, and decodes the whole model into an in-core scene for
full-detail renders.
The block contents (treelets, voxels, triangle blocks) are produced and walked by the
native core; their bit layouts are in native/include/vastray/format.h.
"""

from __future__ import annotations

import math
import os
import struct
import zlib
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from vastray import native
from vastray.direct_io import DirectFile

# The format's constants have one home, native/include/vastray/format.h.
_F = native.FORMAT
MAGIC: bytes = _F["magic"]  # ends in \x1a, which stops `type`/`cat` from dumping binary
VERSION: int = _F["version"]  # what the writer writes
OLDEST_VERSION: int = _F["oldest_version"]  # versions 1-7: version 8 without its later additions
HEADER_SIZE: int = _F["header_size"]
BLOCK_SIZE: int = _F["block_size"]
CODEC_STORED: int = _F["codec_stored"]  # raw bytes (compression would not have saved space)
CODEC_LZ4: int = _F["codec_lz4"]  # LZ4 block format, no frame
CODEC_FAMILY_LZ4: int = _F["codec_family_lz4"]
FLAG_COLOURS: int = _F["flag_colours"]
FLAG_TRIANGLE_IDS: int = _F["flag_triangle_ids"]
FLAG_PART_IDS: int = _F["flag_part_ids"]  # the file ends in a parts section (version 2)
# 4-byte basic nodes whose split is a step of their cell's grid (version 3)
FLAG_QUANTIZED_SPLITS: int = _F["flag_quantized_splits"]
# Vertices on a grid of the root cell, bit-packed offsets per triangle block (FORMAT.md §11)
FLAG_QUANTIZED_VERTICES: int = _F["flag_quantized_vertices"]
# Each level split into streams by coarseness tier, T of them per level (version 5, §5, §15)
FLAG_TIERED: int = _F["flag_tiered"]
TIER_SHIFT: int = _F["tier_shift"]  # a node's block reference: tier << TIER_SHIFT | relative id
MAX_TIERS: int = _F["max_tiers"]
# Compact triangle blocks: bit-packed leaf records, grouped triangles, a palette (§11a)
FLAG_COMPACT_TRIANGLES: int = _F["flag_compact_triangles"]
# Treelets on 4-byte boundaries, LOD words in 4-byte units; with quantized splits (version 7, §8)
FLAG_PACKED_TREELETS: int = _F["flag_packed_treelets"]
FLAG_VOXEL_ERRORS: int = _F["flag_voxel_errors"]
COMPACT_HEADER: int = _F["compact_header"]  # bytes of a compact block's header
COMPACT_GROUP: int = _F["compact_group"]  # triangles per group
VERTEX_GRID_BITS: int = _F["vertex_grid_bits"]  # |grid index| < 2^20
SPLIT_BITS: int = _F["split_bits"]
SPLIT_STEPS: int = 1 << SPLIT_BITS


def dequantize_split(lo: float, hi: float, q: int) -> float:
    """The split plane of step `q` of the cell [lo, hi] on its axis (FLAG_QUANTIZED_SPLITS):
    float32((lo * (2^20 - q) + hi * q) * 2^-20) with the sum in float64, as format.h has it
    (both products are exact in float64, so every reader gets the same float32)."""
    return float(np.float32((float(lo) * (SPLIT_STEPS - q) + float(hi) * q) * (1.0 / SPLIT_STEPS)))


def quantize_split(lo: float, hi: float, target: float) -> float | None:
    """The plane of the grid of [lo, hi] nearest `target`, strictly inside the cell, or
    None when the cell is too narrow for one."""
    lo, hi = float(lo), float(hi)
    if not (hi > lo and np.isfinite(lo) and np.isfinite(hi)):
        return None
    t = (float(target) - lo) / (hi - lo) * SPLIT_STEPS
    q = int(np.floor(min(max(t, 1.0), SPLIT_STEPS - 1.0) + 0.5))
    s = dequantize_split(lo, hi, q)
    return s if lo < s < hi else None


def vertex_grid_steps(lo: Any, hi: Any) -> tuple[float, float, float]:
    """The quantized vertex grid's step per axis for the root cell [lo, hi]
    (FLAG_QUANTIZED_VERTICES): the smallest power of two (at least 2^-126) whose 2^20
    steps reach past max(|lo|, |hi|)."""
    return native.vertex_grid_steps([float(x) for x in lo], [float(x) for x in hi])


def _pad4(n: int) -> int:
    return (n + 3) & ~3


NO_PART: int = _F["no_part"]  # a run's part for triangles in no part

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
    # version 2: the parts section (all zero without one; padding in version 1)
    ("parts_offset", "Q"),
    ("parts_size", "Q"),
    ("parts_crc32", "I"),
    ("part_count", "I"),
    # version 5: tiers per level with FLAG_TIERED, else zero (padding before)
    ("tier_count", "I"),
    # version 6: the six-sample voxels stored packed, in four words (padding before)
    ("voxels_packed", "Q"),
    # since December 2026, without a new version: which way is up in the model, a unit
    # vector; zero (what every earlier writer left in this padding): not said
    ("up", "3f"),
)
_HEADER_STRUCT = struct.Struct("<" + "".join(code for _, code in _HEADER_FIELDS))


def _field_offset(name: str) -> int:
    codes = [code for _, code in _HEADER_FIELDS[: [n for n, _ in _HEADER_FIELDS].index(name)]]
    return struct.calcsize("<" + "".join(codes))


_HEADER_CRC_AT = _field_offset("header_crc32")
assert _HEADER_STRUCT.size <= HEADER_SIZE and _HEADER_CRC_AT == _F["header_crc_at"]
assert _field_offset("parts_offset") == _F["parts_offset_at"]
assert _field_offset("tier_count") == _F["tier_count_at"]
# One per stream (a level, or a tier of a level in a tiered file): first block, block
# count, then what it holds: node levels count their nodes and LOD voxels, the triangle
# level its triangle records and vertices.
_LEVEL = struct.Struct("<IIQQ")
_ENTRY = struct.Struct("<QIIII")  # offset, stored size, raw size, crc32 of stored bytes, codec
assert _LEVEL.size == _F["level_record"] and _ENTRY.size == _F["entry_record"]
# The parts section: part count and run count, then per part its world bounds (f64),
# kept triangles and name (offset, length into the names blob), then the runs (first
# input triangle id, part), then the names blob (UTF-8).
_PARTS_HEAD = struct.Struct("<II")
_PART = np.dtype([("lo", "<f8", (3,)), ("hi", "<f8", (3,)), ("triangles", "<u8"), ("name_offset", "<u4"),
                  ("name_length", "<u4")])  # fmt: skip
_RUN = np.dtype([("first", "<u4"), ("part", "<u4")])
assert _PARTS_HEAD.size == _F["parts_head"] and _PART.itemsize == _F["part_record"]
assert _RUN.itemsize == _F["run_record"]


class ModelError(ValueError):
    """A model file that is not a model, is damaged, or has an unsupported version."""


@dataclass(frozen=True)
class ModelPart:
    """One part of the input as stored in the model: `id` is its index in the part
    table, `lo`/`hi` the world bounds of its kept triangles, `triangles` how many."""

    id: int
    name: str
    lo: tuple[float, float, float]
    hi: tuple[float, float, float]
    triangles: int


@dataclass(frozen=True)
class PartTable:
    """What the builder stores as a parts section (docs/FORMAT.md §4a)."""

    names: list[str]
    lo: np.ndarray  # (P, 3) float64 world bounds of each part's kept triangles
    hi: np.ndarray
    triangles: np.ndarray  # (P,) kept triangles per part
    run_firsts: np.ndarray  # (R,) first input triangle id of each run, strictly increasing from 0
    run_parts: np.ndarray  # (R,) part of each run, NO_PART (or -1) for none

    def pack(self) -> bytes:
        blob = bytearray()
        records = np.zeros(len(self.names), _PART)
        for i, name in enumerate(self.names):
            data = name.encode("utf-8")
            records[i]["name_offset"], records[i]["name_length"] = len(blob), len(data)
            blob += data
        records["lo"], records["hi"], records["triangles"] = self.lo, self.hi, self.triangles
        runs = np.zeros(len(self.run_firsts), _RUN)
        runs["first"] = self.run_firsts
        runs["part"] = np.where(np.asarray(self.run_parts, np.int64) < 0, NO_PART, self.run_parts)
        return _PARTS_HEAD.pack(len(records), len(runs)) + records.tobytes() + runs.tobytes() + bytes(blob)


def part_name(obj: str, group: str, material: str) -> str:
    """A part's display name: object, group and material joined by " / ", empty ones
    left out; "(unnamed)" when all are empty."""
    return " / ".join(n for n in (obj, group, material) if n) or "(unnamed)"


@dataclass(frozen=True)
class Stream:
    """One stream of blocks: a level (untiered) or one coarseness tier of a level.
    `items` and `extra` count what the level table says it holds (§5)."""

    level: int
    tier: int
    first: int
    count: int
    items: int
    extra: int


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


@dataclass(frozen=True)
class FileRange:
    """`size` bytes at `offset` of the open file `fd`, for write_model_file to copy
    without passing them through Python."""

    fd: int
    offset: int
    size: int


def pack_head(
    fields: dict[str, Any],
    levels: list[tuple[int, int, int, int]],
    entries: list[tuple[int, int, int, int]],
    offsets: Sequence[int],
    blocks_end: int,
    section: bytes,
    part_count: int,
    tier_count: int = 0,
) -> tuple[bytes, bytes]:
    """The header and the block index of a file whose blocks lie at `offsets` (absolute,
    any order, no overlaps) below `blocks_end`, where the parts `section` (empty: none)
    starts. `levels`, `entries` as in write_model_file."""
    if tier_count and len(levels) % tier_count:
        raise ValueError("a tiered level table holds tier_count records per level")
    index = bytearray()
    for first, count, items, extra in levels:
        index += _LEVEL.pack(first, count, items, extra)
    for offset, (stored, raw, crc, codec) in zip(offsets, entries, strict=True):
        index += _ENTRY.pack(offset, stored, raw, crc, codec)
    header = dict(fields)
    header.setdefault("up", (0.0, 0.0, 0.0))  # (not said)
    if section:
        header["flags"] = header["flags"] | FLAG_PART_IDS
    else:
        header["flags"] = header["flags"] & ~FLAG_PART_IDS
    if tier_count:
        header["flags"] = header["flags"] | FLAG_TIERED
    else:
        header["flags"] = header["flags"] & ~FLAG_TIERED
    header.update(
        magic=MAGIC,
        version=VERSION,
        header_size=HEADER_SIZE,
        block_size=BLOCK_SIZE,
        codec=CODEC_FAMILY_LZ4,
        level_count=len(levels) // max(1, tier_count),
        tier_count=tier_count,
        block_count=len(entries),
        index_offset=HEADER_SIZE,
        data_offset=HEADER_SIZE + len(index),
        raw_bytes=sum(e[1] for e in entries),
        file_size=blocks_end + len(section),
        index_crc32=zlib.crc32(index),
        header_crc32=0,
        parts_offset=blocks_end if section else 0,
        parts_size=len(section),
        parts_crc32=zlib.crc32(section) if section else 0,
        part_count=part_count if section else 0,
    )
    return _pack_header(header), bytes(index)


def write_model_file(
    out: DirectFile,
    fields: dict[str, Any],
    levels: list[tuple[int, int, int, int]],
    entries: list[tuple[int, int, int, int]],
    block_data: Iterator[bytes | FileRange],
    section: bytes = b"",
    part_count: int = 0,
    tier_count: int = 0,
) -> int:
    """Writes header, index, blocks and the parts `section` (packed, of `part_count`
    parts; empty: none), the blocks one after the other in id order. `levels` are the
    level table's records (first, count, items, extra): one per level, or with
    `tier_count` > 0 (FLAG_TIERED) that many per level, level-major. `entries` are
    (stored size, raw size, crc, codec) in block order; `block_data` yields the stored
    bytes in the same order (it may yield them in larger runs), as bytes or as ranges
    of other files, which `out` (direct_io.py) copies past the page cache. Returns the
    file size."""
    data_offset = HEADER_SIZE + _LEVEL.size * len(levels) + _ENTRY.size * len(entries)
    offsets = []
    offset = data_offset
    for stored, *_ in entries:
        offsets.append(offset)
        offset += stored
    header, index = pack_head(fields, levels, entries, offsets, offset, section, part_count, tier_count)
    out.write(header)
    out.write(index)
    written = data_offset
    for chunk in block_data:
        if isinstance(chunk, FileRange):
            out.copy(chunk.fd, chunk.offset, chunk.size)
            written += chunk.size
        else:
            out.write(chunk)
            written += len(chunk)
    if written != offset:
        raise RuntimeError(f"wrote {written} bytes but the index describes {offset}")
    out.write(section)
    return offset + len(section)


def part_of(firsts: np.ndarray, parts: np.ndarray, triangle_ids: Any, input_triangles: int) -> np.ndarray:
    """The part of each triangle id from runs (`ModelFile.part_runs`): int32, -1 for
    none, for ids < 0 and for ids >= input_triangles."""
    ids = np.asarray(triangle_ids)
    if ids.dtype.kind not in "iu":
        raise TypeError(f"triangle ids must be integers, got {ids.dtype}")
    ids = ids.astype(np.int64)
    if len(firsts) == 0:
        return np.full(ids.shape, -1, np.int32)
    run = np.searchsorted(firsts.astype(np.int64), ids, side="right") - 1
    out = parts[np.clip(run, 0, len(parts) - 1)].astype(np.int32)
    out[(ids < 0) | (ids >= input_triangles) | (run < 0)] = -1
    return out


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
        if not OLDEST_VERSION <= h["version"] <= VERSION:
            raise self._fail(
                f"format version {h['version']} is not supported (this vastray reads versions "
                f"{OLDEST_VERSION} to {VERSION}); rebuild the model with this version"
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
        known = FLAG_COLOURS | FLAG_TRIANGLE_IDS | (FLAG_PART_IDS if h["version"] >= 2 else 0)
        known |= FLAG_QUANTIZED_SPLITS if h["version"] >= 3 else 0
        known |= FLAG_QUANTIZED_VERTICES if h["version"] >= 4 else 0
        known |= FLAG_TIERED if h["version"] >= 5 else 0
        known |= FLAG_COMPACT_TRIANGLES if h["version"] >= 5 else 0
        known |= FLAG_PACKED_TREELETS if h["version"] >= 7 else 0
        known |= FLAG_VOXEL_ERRORS if h["version"] >= 8 else 0
        if not h["flags"] & FLAG_TRIANGLE_IDS or h["flags"] & ~known:
            raise self._fail(f"unsupported attribute flags {h['flags']:#x}")
        if h["flags"] & FLAG_PACKED_TREELETS and not h["flags"] & FLAG_QUANTIZED_SPLITS:
            raise self._fail("packed treelets flag set without quantized splits")
        if h["flags"] & FLAG_VOXEL_ERRORS and not h["flags"] & FLAG_QUANTIZED_SPLITS:
            raise self._fail("voxel errors flag set without quantized splits")
        if h["version"] < 2:  # bytes 200-255 were padding (zero; the CRC covers them)
            h.update(parts_offset=0, parts_size=0, parts_crc32=0, part_count=0)
        if h["version"] < 5:  # bytes 224-227 were padding
            h.update(tier_count=0)
        if h["version"] < 6:  # bytes 228-235 were padding
            h.update(voxels_packed=0)
        if h["voxels_packed"] > h["voxels_six"]:
            raise self._fail(f"implausible packed voxel count {h['voxels_packed']}")
        up = h["up"]  # a unit vector, or zero (not said)
        if not all(math.isfinite(c) for c in up) or (any(up) and not 0.99 < math.hypot(*up) < 1.01):
            raise self._fail(f"implausible up vector {up}")
        tiered = bool(h["flags"] & FLAG_TIERED)
        if not tiered and h["tier_count"]:
            raise self._fail("tier count set without the tiered flag")
        if tiered and not 1 <= h["tier_count"] <= MAX_TIERS:
            raise self._fail(f"implausible tier count {h['tier_count']}")
        self.header = h
        self.tier_count = h["tier_count"] if tiered else 1
        blocks_end = self._open_parts(h, size)
        records = h["level_count"] * self.tier_count
        index_size = _LEVEL.size * records + _ENTRY.size * h["block_count"]
        if h["index_offset"] + index_size != h["data_offset"] or h["data_offset"] > blocks_end:
            raise self._fail("index does not fit the file")
        self._file.seek(h["index_offset"])
        index = self._file.read(index_size)
        if zlib.crc32(index) != h["index_crc32"]:
            raise self._fail("block index checksum mismatch (the index is corrupted)")
        table = [_LEVEL.unpack_from(index, _LEVEL.size * i) for i in range(records)]
        t = self.tier_count
        # Level-major: record L * T + k is level L's tier k (T = 1 untiered).
        self.streams = [Stream(i // t, i % t, *record) for i, record in enumerate(table)]
        # Per level, over its tiers: (first block, block count), and (nodes, LOD voxels)
        # for node levels, (triangle records, vertices) for the last.
        self.levels = [
            (self.streams[L * t].first, sum(s.count for s in self.streams[L * t : (L + 1) * t]))
            for L in range(h["level_count"])
        ]
        self.level_contents = [
            (
                sum(s.items for s in self.streams[L * t : (L + 1) * t]),
                sum(s.extra for s in self.streams[L * t : (L + 1) * t]),
            )
            for L in range(h["level_count"])
        ]
        base = _LEVEL.size * records
        self.blocks = [
            BlockEntry(*_ENTRY.unpack_from(index, base + _ENTRY.size * i)) for i in range(h["block_count"])
        ]
        expected = 0
        for s in self.streams:
            if s.first != expected:
                raise self._fail("levels do not tile the block index")
            expected += s.count
        if expected != len(self.blocks):
            raise self._fail("levels do not cover every block")
        for i, e in enumerate(self.blocks):
            outside = e.offset < h["data_offset"] or e.offset + e.stored_size > blocks_end
            if outside or e.raw_size > BLOCK_SIZE:
                raise self._fail(f"block {i} lies outside the file or is oversized")

    def _open_parts(self, h: dict[str, Any], size: int) -> int:
        """Reads and checks the parts section (docs/FORMAT.md §4a, §13 checks 12-17);
        returns where the blocks must end."""
        self._parts: list[ModelPart] = []
        self._run_firsts = np.zeros(0, np.uint32)
        self._run_parts = np.zeros(0, np.int32)
        fields = (h["parts_offset"], h["parts_size"], h["parts_crc32"], h["part_count"])
        if not h["flags"] & FLAG_PART_IDS:
            if any(fields):
                raise self._fail("parts fields set without the part-ids flag")
            return size
        offset, length, crc, count = fields
        if count == 0 or length < _PARTS_HEAD.size or offset > size or offset + length != size:
            raise self._fail("parts section does not fit the file")
        self._file.seek(offset)
        data = self._file.read(length)
        if len(data) != length or zlib.crc32(data) != crc:
            raise self._fail("parts section damaged (checksum mismatch)")
        parts, runs = _PARTS_HEAD.unpack_from(data)
        names_at = _PARTS_HEAD.size + _PART.itemsize * parts + _RUN.itemsize * runs
        if parts != count or runs == 0 or names_at > length:
            raise self._fail("parts section does not match its counts")
        records = np.frombuffer(data, _PART, parts, _PARTS_HEAD.size)
        table = np.frombuffer(data, _RUN, runs, _PARTS_HEAD.size + _PART.itemsize * parts)
        firsts = table["first"].copy()
        if firsts[0] != 0 or (runs > 1 and not (np.diff(firsts.astype(np.int64)) > 0).all()):
            raise self._fail("part runs are out of order")
        if int(firsts[-1]) >= max(1, h["input_triangles"]):
            raise self._fail("a part run starts past the last input triangle")
        run_parts = table["part"]
        if ((run_parts >= parts) & (run_parts != NO_PART)).any():
            raise self._fail("a part run names a part outside the part table")
        if int(records["triangles"].sum()) > h["triangle_count"]:
            raise self._fail("the parts hold more triangles than the model")
        blob = data[names_at:]
        out: list[ModelPart] = []
        for i, r in enumerate(records):
            start, n = int(r["name_offset"]), int(r["name_length"])
            if start + n > len(blob):
                raise self._fail(f"part {i}: its name lies outside the names blob")
            try:
                name = blob[start : start + n].decode("utf-8")
            except UnicodeDecodeError:
                raise self._fail(f"part {i}: its name is not UTF-8") from None
            lo = tuple(float(x) for x in r["lo"])
            hi = tuple(float(x) for x in r["hi"])
            out.append(ModelPart(i, name, lo, hi, int(r["triangles"])))  # type: ignore[arg-type]
        self._parts = out
        self._run_firsts = firsts
        # -1 for no part; written without np.where(uint32, -1, ...), which NumPy 2.5 refuses.
        self._run_parts = run_parts.astype(np.int32)
        self._run_parts[run_parts == NO_PART] = -1
        return offset

    # -- parts -----------------------------------------------------------------------------

    @property
    def parts(self) -> list[ModelPart]:
        """The part table (empty when the input had no parts); `id` is the index."""
        return list(self._parts)

    @property
    def part_runs(self) -> tuple[np.ndarray, np.ndarray]:
        """(first input triangle id of each run, uint32; its part, int32, -1 for none).
        A run covers ids up to the next run's first - 1 (the last: up to input_triangles - 1)."""
        return self._run_firsts.copy(), self._run_parts.copy()

    def part_of(self, triangle_ids: np.ndarray) -> np.ndarray:
        """The part (int32; -1 for none, for ids < 0 and past the input) of each input
        triangle id."""
        return part_of(self._run_firsts, self._run_parts, triangle_ids, self.header["input_triangles"])

    # -- properties ----------------------------------------------------------------------

    @property
    def has_colours(self) -> bool:
        return bool(self.header["flags"] & FLAG_COLOURS)

    @property
    def quantized_splits(self) -> bool:
        """Basic nodes of 4 bytes with split planes on their cell's grid (version 3)."""
        return bool(self.header["flags"] & FLAG_QUANTIZED_SPLITS)

    @property
    def packed_treelets(self) -> bool:
        """Treelets on 4-byte boundaries, LOD words in 4-byte units (version 7, FORMAT.md §8)."""
        return bool(self.header["flags"] & FLAG_PACKED_TREELETS)

    @property
    def voxel_errors(self) -> bool:
        """LOD nodes carry a surface error for their LOD test (version 8, FORMAT.md §8)."""
        return bool(self.header["flags"] & FLAG_VOXEL_ERRORS)

    @property
    def quantized_vertices(self) -> bool:
        """Vertices on the root cell's grid, bit-packed offsets in triangle blocks (version 4)."""
        return bool(self.header["flags"] & FLAG_QUANTIZED_VERTICES)

    @property
    def tiered(self) -> bool:
        """Levels split into streams by coarseness tier (version 5)."""
        return bool(self.header["flags"] & FLAG_TIERED)

    @property
    def up(self) -> tuple[float, float, float] | None:
        """Which way is up in the model, as its builder was told (header bytes 236-247), or
        None where it was not told (zero, as every file before December 2026 has)."""
        up = self.header["up"]
        return (float(up[0]), float(up[1]), float(up[2])) if any(up) else None

    def stream(self, level: int, tier: int) -> Stream:
        """The stream of `level` (0 ... node_levels, the last the triangle level) and tier."""
        if not (0 <= level < len(self.levels) and 0 <= tier < self.tier_count):
            raise IndexError(f"no stream for level {level}, tier {tier}")
        return self.streams[level * self.tier_count + tier]

    def reference(self, word: int) -> tuple[int, int]:
        """(tier, block id relative to the stream) of a block reference stored in a node."""
        if not self.tiered:
            return 0, word
        return word >> TIER_SHIFT, word & ((1 << TIER_SHIFT) - 1)

    @property
    def compact_triangles(self) -> bool:
        """Triangle blocks in the compact layout (version 5, FORMAT.md §11a)."""
        return bool(self.header["flags"] & FLAG_COMPACT_TRIANGLES)

    def triangle_layout(self, data: bytes) -> dict[str, int]:
        """The sections of a triangle block's raw bytes (FORMAT.md §11, §11a): counts, byte
        offsets and, with quantized vertices, the bits per axis and per vertex record.
        Raises ModelError for a damaged packing word or compact header."""
        if self.compact_triangles:
            return self._compact_layout(data)
        entries, tris, verts, packing = struct.unpack_from("<4I", data)
        out = {"entries": entries, "triangles_count": tris, "vertices_count": verts}
        out["triangles"] = 16 + _pad4(2 * entries)
        out["ids"] = out["triangles"] + _pad4(6 * tris)
        out["colours"] = out["ids"] + 4 * tris
        out["vertices"] = out["colours"] + (4 * tris if self.has_colours else 0)
        out["end"] = out["vertices"] + 12 * verts
        if self.quantized_vertices:
            bits = self._vertex_bits(packing)
            record = (sum(bits) + 7) // 8
            out.update(bits_x=bits[0], bits_y=bits[1], bits_z=bits[2], record=record)
            out["end"] = out["vertices"] + 12 + _pad4(record * verts + 8 - record)
        return out

    def _vertex_bits(self, packing: int) -> list[int]:
        bits = [(packing >> (8 * a)) & 0xFF for a in range(3)]
        if packing >> 24 or max(bits) > VERTEX_GRID_BITS + 1:
            raise self._fail(f"triangle block with a damaged vertex packing word {packing:#x}")
        return bits

    def _compact_layout(self, data: bytes) -> dict[str, int]:
        """A compact block (FORMAT.md §11a): header, leaf records, group headers, group
        data, palette and vertices, with the group header width."""
        if len(data) < COMPACT_HEADER:
            raise self._fail("compact triangle block shorter than its header")
        tris, verts, packing, colours, id_min, id_bits, groups, palette = struct.unpack_from("<8I", data)
        if not (1 <= tris and 1 <= verts and id_bits <= 32 and COMPACT_HEADER <= groups <= palette):
            raise self._fail(f"compact triangle block with a damaged header ({tris}, {verts}, {id_bits})")
        header_bits = 16 + (verts - 1).bit_length() + 5 + id_bits + 7
        if self.has_colours:
            header_bits += max(colours - 1, 0).bit_length() + 5
        group_count = -(-tris // COMPACT_GROUP)
        out = {"triangles_count": tris, "vertices_count": verts, "palette_count": colours, "id_min": id_min,
               "id_bits": id_bits, "records": COMPACT_HEADER, "groups": groups, "group_count": group_count,
               "header_bits": header_bits, "data": groups + (group_count * header_bits + 7) // 8,
               "palette": palette, "vertices": palette + 4 * colours}  # fmt: skip
        if self.quantized_vertices:
            bits = self._vertex_bits(packing)
            out.update(bits_x=bits[0], bits_y=bits[1], bits_z=bits[2], record_bits=sum(bits))
            out["end"] = out["vertices"] + 12 + (sum(bits) * verts + 7) // 8 + 8
        else:
            out["end"] = out["vertices"] + 12 * verts
        if out["data"] > palette:
            raise self._fail("compact triangle block whose group headers overrun its data")
        return out

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
                [s.first for s in self.streams],
                list(self.header["centre"]),
                list(self.header["cell_lo"]),
                list(self.header["cell_hi"]),
                self.header["input_triangles"],
                self.has_colours,
                self.quantized_splits,
                self.quantized_vertices,
                self.tier_count,
                self.tiered,
                self.compact_triangles,
                self.packed_treelets,
                self.voxel_errors,
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
            if self.tiered:
                row["tiers"] = [
                    {
                        "tier": s.tier,
                        "blocks": s.count,
                        "items": s.items,
                        "extra": s.extra,
                        "raw_bytes": sum(e.raw_size for e in self.blocks[s.first : s.first + s.count]),
                        "stored_bytes": sum(e.stored_size for e in self.blocks[s.first : s.first + s.count]),
                    }
                    for s in self.streams[level * self.tier_count : (level + 1) * self.tier_count]
                ]
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
            "quantized_splits": self.quantized_splits,
            "packed_treelets": self.packed_treelets,
            "voxel_errors": self.voxel_errors,
            "quantized_vertices": self.quantized_vertices,
            "tiers": self.tier_count if self.tiered else 0,
            "compact_triangles": self.compact_triangles,
            "part_count": len(self._parts),
            "parts": [
                {"id": p.id, "name": p.name, "lo": list(p.lo), "hi": list(p.hi), "triangles": p.triangles}
                for p in self._parts
            ],
            "bounds": self.bounds,
            "centre": list(h["centre"]),
            "nodes": h["basic_nodes"] + h["lod_nodes"] + h["leaves"],
            "basic_nodes": h["basic_nodes"],
            "lod_nodes": h["lod_nodes"],
            "leaves": h["leaves"],
            "voxels": h["voxels_one"] + h["voxels_six"],
            "voxels_one": h["voxels_one"],
            "voxels_six": h["voxels_six"],
            "voxels_packed": h["voxels_packed"],
            "references": h["references"],
            "up": list(self.up) if self.up else None,
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
