"""An independent pure-Python walker of a built model (a test helper).

It reads blocks through `ModelFile.read_block` and decodes them from the bit layouts in
native/include/vastray/format.h alone, without the native decoder: the level table from
the file's bytes (a tiered model's streams, FORMAT.md §5, and the tier and stream-relative
id in every block reference, §7-8), treelets from the
root (level 0, block 0, offset 0), node cells from the root cell and the split planes
(a quantized model's 4-byte basic nodes: the split as a step of the cell, and its
12-byte LOD nodes: the radius from the cell, FORMAT.md §8),
leaves with their triangles (input ids, float32 vertices, colours; a model with quantized
vertices: grid origin plus bit-packed offsets, FORMAT.md §11; compact triangle blocks:
leaf records, group headers and bit-packed group data, §11a) and LOD nodes with
their radius and voxel samples. `walk(model)` yields one `Node` per node in depth-first
order (left before right). `read_parts(path)` reads the parts section (FORMAT.md §4a)
from the file's bytes alone, checking that it follows the last block to the file's end;
`read_up(path)` the header's up (§2).
"""

from __future__ import annotations

import os
import struct
import zlib
from collections.abc import Iterator
from dataclasses import dataclass, field

import numpy as np

from vastray.modelfile import ModelFile

INNER = 1 << 31
LOD = 1 << 30
LEFT_EMPTY = 1 << 2
RIGHT_EMPTY = 1 << 3
ONE_SAMPLE = 1 << 31
PACKED_VOXEL = 1 << 30  # a voxel's first word (version 6): six faces in four words, two colours at most
TREELET_HEIGHT = 3
QUANTIZED_SPLITS = 1 << 3  # header flag (version 3): 4-byte basic nodes, splits as grid steps
SPLIT_STEPS = 1 << 20
QUANTIZED_VERTICES = 1 << 4  # header flag (version 4): vertices on the root cell's grid, packed per block
TIERED = 1 << 6  # header flag (version 5): each level in streams by coarseness tier
TIER_COUNT_AT = 224  # the header's u32 tier count (tiers per level)
UP_AT = 236  # the header's f32[3] up: a unit vector, or zero (not said; padding before)
TIER_SHIFT = 26  # a block reference: tier in bits 26-31, stream-relative id below
COMPACT_TRIANGLES = 1 << 5  # header flag (version 5): compact triangle blocks
PACKED_TREELETS = 1 << 7  # header flag (version 7): LOD words in 4-byte units, treelets unpadded
VOXEL_ERRORS = 1 << 8  # header flag (version 8): a LOD node's word 1 is its split step and an error code
COMPACT_HEADER = 32  # bytes of a compact block's header
GROUP = 8  # triangles per group of a compact block


def grid_step(lo: float, hi: float) -> float:
    """FORMAT.md §11: the smallest power of two S >= 2^-126 with 2^20 * S > max(|lo|, |hi|)."""
    m = max(abs(float(lo)), abs(float(hi)))
    e = -126
    while e < 200 and 2.0 ** (e + 20) <= m:
        e += 1
    return 2.0**e


def dequantize(lo: float, hi: float, q: int) -> float:
    """FORMAT.md §8: float32((lo * (2^20 - q) + hi * q) * 2^-20), the sum in float64."""
    return float(np.float32((np.float64(lo) * (SPLIT_STEPS - q) + np.float64(hi) * q) / SPLIT_STEPS))


class WalkError(ValueError):
    """The model's blocks do not follow the layout in format.h."""


@dataclass
class Node:
    kind: str  # "basic", "lod" or "leaf"
    level: int  # LOD level of the treelet holding the node
    depth: int  # depth inside its treelet (0, 1 or 2)
    lo: np.ndarray  # float32 (3,) cell
    hi: np.ndarray
    tier: int = 0  # the tier of the stream whose block holds the node's treelet
    block: int = 0  # that block's global id
    offset: int = 0  # the node's offset in it
    # inner nodes
    axis: int = -1
    split: float = 0.0
    empty: tuple[bool, bool] = (False, False)  # (left child empty, right child empty)
    # LOD nodes
    radius: float = 0.0
    error: float = 0.0  # what its LOD test compares: the radius, or (version 8) R * (code + 1) / 256
    samples: list[int] = field(default_factory=list)  # 32-bit samples, 1 or 6 (a packed voxel's decoded)
    voxel_words: list[int] = field(default_factory=list)  # the voxel as stored: 1, 4 (packed) or 6 words
    child_tier: int = 0  # the tier of the block holding its child treelets
    # leaves
    tri_tier: int = 0  # the tier of its (first) triangle block
    tri_blocks: list[int] = field(default_factory=list)  # global ids of the blocks its list runs through
    ids: np.ndarray | None = None  # (k,) uint32 input triangle ids
    vertices: np.ndarray | None = None  # (k, 3, 3) float32, relative to the model centre
    colours: np.ndarray | None = None  # (k,) uint32 0x00BBGGRR, when the model has colours

    @property
    def global_depth(self) -> int:
        return TREELET_HEIGHT * self.level + self.depth

    def child_cell(self, side: int) -> tuple[np.ndarray, np.ndarray]:
        lo, hi = self.lo.copy(), self.hi.copy()
        (hi if side == 0 else lo)[self.axis] = np.float32(self.split)
        return lo, hi


def decode_sample(s: int) -> tuple[np.ndarray, np.ndarray]:
    """(colour in [0, 1]^3, unit normal) of one voxel sample (format.h unpack_sample)."""
    colour = np.array([(s >> shift) & 31 for shift in (0, 5, 10)], dtype=np.float64) / 31.0
    axis = ((s >> 16) & 3) % 3

    def s6(v: int) -> float:
        return (v - 64 if v & 32 else v) / 31.0

    n = np.zeros(3)
    n[axis] = -1.0 if (s >> 15) & 1 else 1.0
    n[(axis + 1) % 3] = s6((s >> 18) & 63)
    n[(axis + 2) % 3] = s6((s >> 24) & 63)
    return colour, n / np.linalg.norm(n)


def voxel_samples(words: list[int]) -> list[int]:
    """The samples of a voxel from its stored words (1, 4 or 6 of them): one sample, or
    the six faces' samples (bits 0-29) in face order."""
    first = words[0]
    if first & ONE_SAMPLE:
        return [first]
    if not first & PACKED_VOXEL:
        return list(words[:6])
    # Words 1-3 as one 96-bit field: normals of faces 1-5, colour B, the faces showing B.
    field = words[1] | words[2] << 32 | words[3] << 64
    normals = [(first >> 15) & 0x7FFF] + [(field >> (15 * (f - 1))) & 0x7FFF for f in range(1, 6)]
    a, b = first & 0x7FFF, (field >> 75) & 0x7FFF
    return [(b if (field >> (90 + f)) & 1 else a) | normals[f] << 15 for f in range(6)]


def _pad4(n: int) -> int:
    return (n + 3) & ~3


@dataclass
class TriangleBlock:
    list: np.ndarray  # (entries,) uint16: triangle index in this block
    triangles: np.ndarray  # (tris, 3) uint16: vertex indices
    ids: np.ndarray  # (tris,) uint32
    colours: np.ndarray | None  # (tris,) uint32
    vertices: np.ndarray  # (verts, 3) float32

    @classmethod
    def parse(
        cls, raw: bytes, has_colours: bool, steps: tuple[float, float, float] | None = None
    ) -> TriangleBlock:
        """`steps`: the grid of a model with quantized vertices (None: float32 vertices)."""
        entries, tris, verts, packing = struct.unpack_from("<4I", raw)
        at_tri = 16 + _pad4(2 * entries)
        at_ids = at_tri + _pad4(6 * tris)
        at_col = at_ids + 4 * tris
        at_vert = at_col + (4 * tris if has_colours else 0)
        widths, stride = [], 0
        if steps is None:
            size = 12 * verts
        else:
            widths = axis_bits(packing)
            record = (sum(widths) + 7) // 8  # whole bytes per vertex record
            stride = 8 * record
            size = 12 + _pad4(record * verts + 8 - record)
        if at_vert + size != len(raw):
            raise WalkError(f"triangle block of {len(raw)} bytes does not match its section counts")
        vertices = block_vertices(raw, at_vert, verts, steps, widths, stride)
        return cls(
            np.frombuffer(raw, "<u2", entries, 16),
            np.frombuffer(raw, "<u2", 3 * tris, at_tri).reshape(tris, 3),
            np.frombuffer(raw, "<u4", tris, at_ids),
            np.frombuffer(raw, "<u4", tris, at_col) if has_colours else None,
            vertices,
        )


def read_streams(path: str | os.PathLike[str]) -> tuple[int, list[list[tuple[int, int]]]]:
    """(tiers per level, per level per tier (first block, count)), from the file's header
    and level table alone: level_count x T records, level-major (T = 1 untiered)."""
    with open(path, "rb") as f:
        head = f.read(256)
        version, _, flags = struct.unpack_from("<III", head, 8)
        level_count = struct.unpack_from("<I", head, 28)[0]
        tiers = struct.unpack_from("<I", head, TIER_COUNT_AT)[0] if version >= 5 and flags & TIERED else 1
        index_offset = struct.unpack_from("<Q", head, 160)[0]
        f.seek(index_offset)
        table = f.read(24 * level_count * tiers)
    records = [struct.unpack_from("<II", table, 24 * i) for i in range(level_count * tiers)]
    return tiers, [records[level * tiers : (level + 1) * tiers] for level in range(level_count)]


def read_up(path: str | os.PathLike[str]) -> tuple[float, float, float] | None:
    """Which way is up in the model, from the header's bytes alone (None: not said)."""
    with open(path, "rb") as f:
        head = f.read(256)
    up = struct.unpack_from("<3f", head, UP_AT)
    if up == (0.0, 0.0, 0.0):
        return None
    length = float(np.sqrt(sum(float(c) * float(c) for c in up)))
    if not (np.all(np.isfinite(up)) and abs(length - 1.0) < 0.01):
        raise WalkError(f"the header's up {up} is neither zero nor a unit vector")
    return (float(up[0]), float(up[1]), float(up[2]))


def bits(raw: bytes, pos: int, width: int) -> int:
    """`width` bits at bit `pos` of raw (bit i is bit i % 8 of byte i // 8); past the end
    reads zeros (the callers check extents first)."""
    start = pos >> 3
    return (int.from_bytes(raw[start : start + 9], "little") >> (pos & 7)) & ((1 << width) - 1)


class BitReader:
    """Consecutive fields from bit `pos` of raw."""

    def __init__(self, raw: bytes, pos: int) -> None:
        self.raw, self.pos = raw, pos

    def __call__(self, width: int) -> int:
        value = bits(self.raw, self.pos, width)
        self.pos += width
        return value


def axis_bits(packing: int) -> list[int]:
    """The bits per axis of a quantized block's vertex records (its packing word)."""
    widths = [packing & 0xFF, (packing >> 8) & 0xFF, (packing >> 16) & 0xFF]
    if packing >> 24 or max(widths) > 21:
        raise WalkError(f"vertex packing word {packing:#x} is damaged")
    return widths


def block_vertices(
    raw: bytes, at: int, count: int, steps: tuple[float, float, float] | None, widths: list[int], stride: int
) -> np.ndarray:
    """A triangle block's vertex section at byte `at`: float32 xyz, or (with `steps`) a
    grid origin (3 x i32) and then a record of x, y, z offsets (`widths` bits) every
    `stride` bits, each vertex (origin + offset) * step (exact: a power of two)."""
    if steps is None:
        return np.frombuffer(raw, "<f4", 3 * count, at).reshape(count, 3)
    origin = struct.unpack_from("<3i", raw, at)
    vertices = np.empty((count, 3), np.float32)
    for v in range(count):
        r = BitReader(raw, 8 * (at + 12) + v * stride)
        for a in range(3):
            vertices[v, a] = np.float32(origin[a] + r(widths[a])) * np.float32(steps[a])
    return vertices


@dataclass
class CompactBlock:
    """A compact triangle block (FORMAT.md §11a), every group decoded up front."""

    raw: bytes
    records_end: int  # byte offset of the group headers: leaf records lie before it
    triangles: np.ndarray  # (tris, 3) int64: vertex indices
    ids: np.ndarray  # (tris,) uint32
    colours: np.ndarray | None  # (tris,) uint32 0x00BBGGRR
    vertices: np.ndarray  # (verts, 3) float32

    @classmethod
    def parse(cls, raw: bytes, has_colours: bool, steps: tuple[float, float, float] | None) -> CompactBlock:
        if len(raw) < COMPACT_HEADER:
            raise WalkError("compact triangle block shorter than its header")
        tris, verts, packing, n_colours, id_min, id_bits, groups, palette = struct.unpack_from("<8I", raw)
        if tris == 0 or verts == 0 or id_bits > 32 or (n_colours == 0) == has_colours or n_colours > tris:
            raise WalkError(f"compact header counts are damaged: {tris}, {verts}, {n_colours}, {id_bits}")
        vertex_bits = (verts - 1).bit_length()
        palette_bits = (n_colours - 1).bit_length() if has_colours else 0
        width = 16 + vertex_bits + 5 + id_bits + 6 + 1 + (palette_bits + 5 if has_colours else 0)
        n_groups = (tris + GROUP - 1) // GROUP
        data = groups + (n_groups * width + 7) // 8
        at_vertices = palette + 4 * n_colours
        widths, stride = [], 0
        if steps is None:
            if packing != 0:
                raise WalkError("a compact block of float32 vertices with a packing word")
            size = 12 * verts
        else:
            widths = axis_bits(packing)
            stride = sum(widths)  # vertex records back to back, bit after bit
            size = 12 + (stride * verts + 7) // 8 + 8
        if not COMPACT_HEADER <= groups <= data <= palette or at_vertices + size != len(raw):
            raise WalkError(f"compact triangle block of {len(raw)} bytes does not match its section offsets")
        triangles = np.empty((tris, 3), np.int64)
        ids = np.empty(tris, np.int64)
        indices = np.zeros(tris, np.int64)
        for j in range(n_groups):
            h = BitReader(raw, 8 * groups + j * width)
            offset, corner_base, cw, id_base, iw = h(16), h(vertex_bits), h(5), h(id_bits), h(6)
            split = h(1)
            palette_base, pw = (h(palette_bits), h(5)) if has_colours else (0, 0)
            if cw > 16 or iw > 32 or pw > 16:
                raise WalkError(f"group {j} has field widths {cw}, {iw}, {pw}")
            first, n = GROUP * j, min(GROUP, tris - GROUP * j)
            d = BitReader(raw, 8 * (data + offset))
            d.pos += 3 * cw * n
            # Split: a second id base (its distance from the first), and a bit per id to pick.
            distance_bits = d(6) if split else 0
            distance = d(distance_bits) if split else 0
            if distance_bits > 32:
                raise WalkError(f"group {j} has a second id base of {distance_bits} bits")
            if d.pos + n * (iw + split + pw) > 8 * palette:
                raise WalkError(f"group {j} runs past the group data")
            d.pos = 8 * (data + offset)
            for t in range(first, first + n):
                triangles[t] = [corner_base + d(cw) for _ in range(3)]
            d.pos += 6 + distance_bits if split else 0
            for t in range(first, first + n):
                field = d(iw + split)
                ids[t] = id_min + id_base + (distance if field & split else 0) + (field >> split)
            for t in range(first, first + n):
                indices[t] = palette_base + d(pw)
        if (triangles >= verts).any():
            raise WalkError("a triangle points past the vertex section")
        if (ids >= 1 << 32).any():
            raise WalkError("a triangle id does not fit 32 bits")
        colours = None
        if has_colours:
            if (indices >= n_colours).any():
                raise WalkError("a triangle's colour points past the palette")
            colours = np.frombuffer(raw, "<u4", n_colours, palette)[indices]
        vertices = block_vertices(raw, at_vertices, verts, steps, widths, stride)
        return cls(raw, groups, triangles, ids.astype(np.uint32), colours, vertices)

    def record(self, at: int, remaining: int) -> np.ndarray:
        """The triangle indices of the leaf record at byte `at`, for a leaf with
        `remaining` entries not read yet."""
        if not COMPACT_HEADER <= at < self.records_end:
            raise WalkError(f"leaf record at byte {at} lies outside the records")
        r = BitReader(self.raw, 8 * at)
        nxt, width, partial = r(16), r(5), r(1)
        count = r(16) if partial else remaining
        if width > 16 or not 1 <= count <= remaining:
            raise WalkError(f"leaf record at byte {at} has width {width} and count {count} of {remaining}")
        # The entries' bits as one string, bit i at index i (past the block's end: zeros,
        # as `bits` reads), sliced per entry: a leaf holds up to thousands of entries.
        most = count * (1 + width)
        first = r.pos
        value = int.from_bytes(self.raw[first >> 3 : (first + most + 7) >> 3], "little") >> (first & 7)
        stream = format(value, f"0{most}b")[::-1][:most]
        entries: list[int] = []
        at_bit = 0
        for _ in range(count):
            if stream[at_bit] == "1":
                entries.append(nxt)
                nxt += 1
                at_bit += 1
            else:
                d = int(stream[at_bit + width : at_bit : -1], 2) if width else 0
                if d >= nxt:
                    raise WalkError(f"leaf record at byte {at} reaches back before the first triangle")
                entries.append(nxt - 1 - d)
                at_bit += 1 + width
        r.pos = first + at_bit
        local = np.array(entries, np.int64)
        if r.pos > 8 * self.records_end:
            raise WalkError(f"leaf record at byte {at} runs past the records")
        if (local >= len(self.ids)).any():
            raise WalkError(f"leaf record at byte {at} points past the triangles")
        return local


class Walker:
    def __init__(self, model: ModelFile) -> None:
        self.model = model
        self.tiers, self.streams = read_streams(model.path)
        self.tiered = bool(model.header["flags"] & TIERED)
        self.tri_level = len(self.streams) - 1
        self.raw: dict[int, bytes] = {}  # the blocks read so far, by block id
        self.tri_blocks: dict[int, TriangleBlock | CompactBlock] = {}  # parsed so far, by global block id
        self.compact = bool(model.header["version"] >= 5 and model.header["flags"] & COMPACT_TRIANGLES)

    def resolve(self, level: int, reference: int) -> tuple[int, int, int]:
        """(tier, global block id, end of its stream) of a block reference in `level`."""
        tier, relative = 0, reference
        if self.tiered:
            tier, relative = reference >> TIER_SHIFT, reference & ((1 << TIER_SHIFT) - 1)
        if tier >= self.tiers:
            raise WalkError(f"block reference {reference:#x} names tier {tier} of {self.tiers}")
        first, count = self.streams[level][tier]
        if not 0 <= relative < count:
            raise WalkError(f"block {relative} is outside level {level} tier {tier} ({count} blocks)")
        return tier, first + relative, first + count

    def read(self, block: int) -> bytes:
        if block not in self.raw:
            self.raw[block] = self.model.read_block(block)
        return self.raw[block]

    def word(self, data: bytes, off: int) -> int:
        if off + 4 > len(data):
            raise WalkError(f"node word at {off} runs past the block end ({len(data)} bytes)")
        return struct.unpack_from("<I", data, off)[0]

    def triangles(self, block: int) -> TriangleBlock | CompactBlock:
        if block not in self.tri_blocks:
            raw = self.read(block)
            h = self.model.header
            steps = None
            if h["flags"] & QUANTIZED_VERTICES:
                steps = tuple(grid_step(a, b) for a, b in zip(h["cell_lo"], h["cell_hi"], strict=True))
            parse = CompactBlock.parse if self.compact else TriangleBlock.parse
            self.tri_blocks[block] = parse(raw, self.model.has_colours, steps)
        return self.tri_blocks[block]

    def leaf(self, node: Node, first: int, count: int, reference: int) -> Node:
        """A leaf's list entries run from `first` to the end of its triangle block's list
        and, for a leaf too big for one block, on from entry 0 of the following blocks of
        its stream. In compact blocks `first` is the byte offset of the leaf's record, and
        a leaf goes on with the first record of the following blocks. A leaf of no
        triangles reads no block (its reference is not checked)."""
        ids: list[np.ndarray] = []
        vertices: list[np.ndarray] = []
        colours: list[np.ndarray] = []
        if count == 0:
            node.tri_tier = reference >> TIER_SHIFT if self.tiered else 0
            node.ids, node.vertices = np.zeros(0, np.uint32), np.zeros((0, 3, 3), np.float32)
            node.colours = self._no_colours()
            return node
        node.tri_tier, block, end = self.resolve(self.tri_level, reference)
        while count > 0:
            if block >= end:
                raise WalkError("leaf list runs past the last triangle block of its stream")
            tb = self.triangles(block)
            node.tri_blocks.append(block)
            if isinstance(tb, CompactBlock):
                # `first` is the record's byte offset; a leaf continues at the next
                # block's first record.
                local = tb.record(first, count)
                first = COMPACT_HEADER
            else:
                if first > len(tb.list):
                    raise WalkError("leaf list starts past the list section")
                local = tb.list[first : first + count].astype(np.int64)
                first = 0
            ids.append(tb.ids[local])
            vertices.append(tb.vertices[tb.triangles[local].astype(np.int64)])
            if tb.colours is not None:
                colours.append(tb.colours[local])
            count -= len(local)
            block += 1
        node.ids = np.concatenate(ids) if ids else np.zeros(0, np.uint32)
        node.vertices = np.concatenate(vertices) if vertices else np.zeros((0, 3, 3), np.float32)
        node.colours = np.concatenate(colours) if colours else self._no_colours()
        return node

    def _no_colours(self) -> np.ndarray | None:
        return np.zeros(0, np.uint32) if self.model.has_colours else None

    def walk(self) -> Iterator[Node]:
        h = self.model.header
        lo = np.array(h["cell_lo"], dtype=np.float32)
        hi = np.array(h["cell_hi"], dtype=np.float32)
        # (level, tier, global block, offset, treelet depth, cell); the root is block 0
        first, count = self.streams[0][0]
        if (first, count) != (0, 1):
            raise WalkError("level 0 is not the root's single block, in tier 0")
        stack = [(0, 0, 0, 0, 0, lo, hi)]
        quantized = bool(h["version"] >= 3 and h["flags"] & QUANTIZED_SPLITS)
        packed_treelets = bool(h["version"] >= 7 and h["flags"] & PACKED_TREELETS)
        if packed_treelets and not quantized:
            raise WalkError("packed treelets without quantized splits")
        voxel_errors = bool(h["version"] >= 8 and h["flags"] & VOXEL_ERRORS)
        if voxel_errors and not quantized:
            raise WalkError("voxel errors without quantized splits")
        # A LOD word's fields (shift, width, unit in bytes): voxel, right from left, first child.
        lod_fields = ((4, 5, 4), (9, 6, 4), (15, 15, 4))
        if not packed_treelets:
            lod_fields = ((4, 7, 4), (11, 6, 8), (17, 13, 8))

        def lod_field(w: int, which: int) -> int:
            shift, width, unit = lod_fields[which]
            return unit * ((w >> shift) & ((1 << width) - 1))

        while stack:
            level, tier, block, off, depth, lo, hi = stack.pop()
            data = self.read(block)
            w, w1 = self.word(data, off), self.word(data, off + 4)
            if not w & INNER:
                leaf = Node("leaf", level, depth, lo, hi, tier=tier, block=block, offset=off)
                yield self.leaf(leaf, w & 0xFFFF, (w >> 16) & 0x7FFF, w1)
                continue
            kind = "lod" if w & LOD else "basic"
            node = Node(kind, level, depth, lo, hi, tier=tier, block=block, offset=off)
            node.axis = w & 3
            has_l, has_r = not w & LEFT_EMPTY, not w & RIGHT_EMPTY
            node.empty = (not has_l, not has_r)
            if node.axis > 2:
                raise WalkError(f"split axis {node.axis}")
            small = quantized and not w & LOD  # a 4-byte basic node
            if small:
                node.split = dequantize(lo[node.axis], hi[node.axis], (w >> 10) & (SPLIT_STEPS - 1))
            elif w & LOD and voxel_errors:  # word 1: split step in bits 0-19, error code in 20-27
                if w1 >> 28 or not w1 & (SPLIT_STEPS - 1):
                    raise WalkError(f"LOD split word {w1:#x} out of range")
                node.split = dequantize(lo[node.axis], hi[node.axis], w1 & (SPLIT_STEPS - 1))
            else:
                node.split = float(np.frombuffer(struct.pack("<I", w1), "<f4")[0])
            if w & LOD:
                voxel = off + lod_field(w, 0)
                if quantized:  # a 12-byte LOD node: the radius is half the cell's diagonal
                    ext = (hi - lo).astype(np.float32)
                    node.radius = float(np.float32(0.5) * np.sqrt(np.float32(ext @ ext)))
                else:
                    node.radius = float(np.frombuffer(data[off + 8 : off + 12], "<f4")[0])
                node.error = node.radius
                if voxel_errors:  # (code + 1) / 256 is exact in f32: one rounding, as the readers do
                    code = (w1 >> 20) & 255
                    node.error = float(np.float32(node.radius) * np.float32(code + 1) / np.float32(256))
                first_sample = self.word(data, voxel)
                packed = not first_sample & ONE_SAMPLE and first_sample & PACKED_VOXEL
                if packed and h["version"] < 6:
                    raise WalkError(f"a packed voxel in a version-{h['version']} file")
                n = 1 if first_sample & ONE_SAMPLE else (4 if packed else 6)
                node.voxel_words = [self.word(data, voxel + 4 * i) for i in range(n)]
                node.samples = voxel_samples(node.voxel_words)
                child_level = level + 1
                if child_level >= self.tri_level:
                    raise WalkError("LOD node in the last node level")
                reference = self.word(data, off + (8 if quantized else 12))
                child_tier, child_block, _ = self.resolve(child_level, reference)
                node.child_tier = child_tier
                l_off = lod_field(w, 2)
                r_off = l_off + lod_field(w, 1) if has_l else l_off
                child_depth = 0
            else:
                child_level, child_tier, child_block, child_depth = level, tier, block, depth + 1
                size = 4 if small else 8
                l_off = off + size
                r_off = off + size * ((w >> 4) & 63) if has_l else off + size
            yield node
            # Right first on the stack so the left subtree is walked first.
            if has_r:
                stack.append((child_level, child_tier, child_block, r_off, child_depth, *node.child_cell(1)))
            if has_l:
                stack.append((child_level, child_tier, child_block, l_off, child_depth, *node.child_cell(0)))


def walk(model: ModelFile) -> Iterator[Node]:
    """Every node of `model`, depth first, left before right."""
    return Walker(model).walk()


@dataclass
class PartsSection:
    """The parts section as this walker reads it from the bytes alone (FORMAT.md §4a)."""

    names: list[str]
    lo: np.ndarray  # (P, 3) float64
    hi: np.ndarray
    triangles: np.ndarray  # (P,) uint64
    run_firsts: np.ndarray  # (R,) uint32
    run_parts: np.ndarray  # (R,) uint32, 0xFFFFFFFF for none


def read_parts(path: str | os.PathLike[str]) -> PartsSection | None:
    """Reads the header's parts fields and the parts section without ModelFile, checks
    the file layout around it (the blocks end where it starts, it ends at file_size) and
    its checksum; None when the file has no parts section."""
    data = open(path, "rb").read()
    version, _, flags = struct.unpack_from("<III", data, 8)
    level_count = struct.unpack_from("<I", data, 28)[0]
    block_count, index_offset, data_offset, _, file_size = struct.unpack_from("<5Q", data, 152)
    if file_size != len(data):
        raise WalkError("file_size differs from the file")
    parts_offset, parts_size, parts_crc, part_count = (
        struct.unpack_from("<QQII", data, 200) if version >= 2 else (0, 0, 0, 0)
    )
    # The blocks, in file order, do not overlap, lie past the index with nothing but zero
    # bytes between them (FORMAT.md §3: any order), and end where the parts section (or
    # the file) starts; a tiered model's level table has a record per stream.
    tiers = struct.unpack_from("<I", data, TIER_COUNT_AT)[0] if version >= 5 and flags & TIERED else 1
    entry_at = index_offset + 24 * level_count * tiers
    placed = sorted((*struct.unpack_from("<QI", data, entry_at + 24 * i), i) for i in range(block_count))
    end = data_offset
    for offset, stored, i in placed:
        if offset < end:
            raise WalkError(f"block {i} overlaps the index or the block before it in the file")
        if any(data[end:offset]):
            raise WalkError(f"the bytes before block {i} are not zero padding")
        end = offset + stored
    if not flags & 4:
        if (parts_offset, parts_size, parts_crc, part_count) != (0, 0, 0, 0) or end != file_size:
            raise WalkError("no parts flag, but parts fields or bytes after the blocks")
        return None
    if end != parts_offset or parts_offset + parts_size != file_size:
        raise WalkError("the parts section does not follow the last block to the end of the file")
    section = data[parts_offset:]
    if zlib.crc32(section) != parts_crc:
        raise WalkError("parts section checksum mismatch")
    parts, runs = struct.unpack_from("<II", section, 0)
    if parts != part_count:
        raise WalkError("part counts differ")
    names_at = 8 + 64 * parts + 8 * runs
    lo, hi, tris, names = [], [], [], []
    for i in range(parts):
        rec = struct.unpack_from("<3d3dQII", section, 8 + 64 * i)
        lo.append(rec[0:3])
        hi.append(rec[3:6])
        tris.append(rec[6])
        names.append(section[names_at + rec[7] : names_at + rec[7] + rec[8]].decode("utf-8"))
    table = struct.unpack_from(f"<{2 * runs}I", section, 8 + 64 * parts)
    return PartsSection(
        names,
        np.array(lo, dtype=np.float64).reshape(-1, 3),
        np.array(hi, dtype=np.float64).reshape(-1, 3),
        np.array(tris, dtype=np.uint64),
        np.array(table[0::2], dtype=np.uint32),
        np.array(table[1::2], dtype=np.uint32),
    )
