"""Builds the out-of-core model from any triangle input within a memory budget
(paper 000 §4; the file format is in docs/FORMAT.md).

Phases, each reported through `progress` with one honest total:
1. scan   What must be known before the triangles can be read: a text file (OBJ, ASCII
          PLY or STL, OFF) is parsed into staged binary arrays (bytes of the file); the
          bounds of a soup (binary STL, raw float32) take a pass over its triangles; a
          generated scene is staged in double precision (triangles). Indexed binary
          files (PLY, glTF) only read their vertices for the bounds, fast enough to
          show no phase of their own.
2. read   One pass over the triangles (as the file holds them, polygons and strips
          triangulated in file order) makes model-local float32 records relative to
          the model centre, kept in double, with each triangle's input id (and colour);
          degenerate triangles (zero area in those coordinates: repeated or collinear
          corners) are dropped and counted. An input that fits in one in-core part
          stays in memory; a bigger one is sifted straight into the eight cells of the
          first out-of-core treelet as it is read.
3. split  While a cell holds more triangles than the budget lets us build in core, one
          pass over its scratch file sifts them into the eight cells of three
          median-split levels (a whole treelet). Straddling triangles go to every cell
          they touch.
4. build  Each part that fits is handed to the native writer, which builds its kd-tree
          with binned SAH and empty-space cutting on all cores, samples the LOD voxels,
          emits treelets and triangle blocks, and compresses and checksums them into
          one scratch file per LOD level. The out-of-core treelets above the parts are
          then written bottom-up.
5. write  The header, the block index and the level files are assembled into a
          temporary file that is renamed over the output.
Nothing is left behind on failure, cancellation or Ctrl-C: scratch files and the
temporary output are removed.
"""

from __future__ import annotations

import math
import mmap
import numbers
import os
import queue
import resource
import shutil
import tempfile
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np

from vastray import model_assembly, modelfile, native
from vastray.camera import unit_up
from vastray.mesh import MeshError, PartName
from vastray.sources import SOURCE_HELP, is_model_file, parse_scene
from vastray.triangle_readers import TriangleChunk, VertexTable

# Peak memory of an in-core part per triangle, measured with bench/build.py on 2 threads
# (peak RSS of 10^7-triangle single-part builds, 132-137 bytes above the idle process):
# the 44-byte records, kd-tree references (28 bytes, about 2.3 per triangle at the
# deepest point of the build), nodes and leaf lists, facets, the writer's pending
# treelets and buffered job blocks. Parts are sized with it.
INCORE_BYTES_PER_TRIANGLE = 150
# The kd build's helper threads each copy the references of the subtree they take, so the
# peak grows with the thread count: 10^7-triangle single-part builds peaked at 99, 131,
# 162, 193, 224 and 255 bytes per triangle on 1, 2, 4, 8, 16 and 32 threads (about 31
# more per doubling; 2.27 GB against the 2 GB budget at 16). Parts are sized for 2
# threads, so that the model does not depend on the thread count; the writer runs on as
# many threads as the largest part leaves room for.
INCORE_BYTES_PER_THREAD_DOUBLING = 32
# The budget covers the builder's working set: streaming chunks and in-core parts. On
# top of it comes a fixed overhead that does not grow with the model: the interpreter,
# numpy, lz4 and the native module (90 MiB measured) plus allocator slack.
STATED_OVERHEAD_BYTES = 128 << 20
# Streaming passes hold a chunk of records plus its float64 corners, bounds and masks.
CHUNK_BYTES_PER_TRIANGLE = 300
MAX_CHUNK = 1 << 19
MIN_INCORE_TRIANGLES = 20_000
MAX_OUT_OF_CORE_LEVELS = 16
DEFAULT_MEMORY = 2 << 30
MAX_INPUT_TRIANGLES = 2**32 - 2  # the format's ids are u32, one value reserved


class BuildCancelledError(Exception):
    """The build was cancelled through its cancel event; nothing was written."""


@dataclass
class BuildProgress:
    phase: str  # scan, read, split, build, write
    done: int
    total: int
    unit: str  # what done/total count: triangles or bytes
    elapsed: float  # seconds since the build started
    message: str = ""


def incore_bytes_per_triangle(threads: int) -> int:
    """Peak bytes per triangle of an in-core part built on `threads` threads (the 2-thread
    measure for 2 or fewer)."""
    doublings = max(0.0, math.log2(max(1, threads)) - 1.0)
    return INCORE_BYTES_PER_TRIANGLE + round(INCORE_BYTES_PER_THREAD_DOUBLING * doublings)


@dataclass
class BuildOptions:
    memory: int = DEFAULT_MEMORY  # bytes; the builder's working set stays within this
    threads: int = 0  # 0: every core
    overwrite: bool = False
    scratch_dir: str | None = None  # default: next to the output
    # A coarse tree (a traversal step costs 4 triangle tests): against equal costs it
    # halves the bytes per triangle (bunny 57 -> 30, plant 70 -> 31) and builds faster;
    # full-detail render speed stayed equal within this machine's noise (docs/FORMAT.md).
    leaf_size: int = 4
    traversal_cost: float = 4.0
    intersection_cost: float = 1.0
    empty_space_ratio: float = 0.15
    voxel_rays: int = 3
    # Split planes on a 2^20-step grid of their cell (format version 3): 4-byte basic
    # nodes; the tree is built on those planes, so images are the same and frames no
    # slower (docs/FORMAT.md, "Measured choices"): on by default.
    quantized_splits: bool = True
    # Vertices snapped to a 2^21-step grid of the root cell before the tree is built,
    # stored as bit-packed offsets from a per-block origin (FLAG_QUANTIZED_VERTICES):
    # lossy, by at most one grid step, and watertight (a shared vertex snaps the same
    # everywhere).
    quantized_vertices: bool = False
    # Coarseness tiers (FLAG_TIERED, docs/FORMAT.md §15): each level's treelet pairs and
    # leaf triangles go to streams by the radius of the LOD node above them, so a far
    # view reads the coarse streams only. Tier 0 holds radii down to R_root / 2^
    # tier_coarse_octaves, then a tier per tier_width halvings; 0 writes one stream per
    # level (the layout of version 4).
    tier_width: float = 1.0
    tier_coarse_octaves: int = 4
    # Triangle blocks in the compact layout (format version 5, FLAG_COMPACT_TRIANGLES):
    # leaf lists, corners, ids and colours in bit fields as narrow as each block allows,
    # still decoded per triangle (docs/FORMAT.md §11a). Lossless and 28-32 % smaller,
    # but full-detail frames decode more per triangle (4-12 % slower, "Measured
    # choices"), so an option.
    compact_triangles: bool = False
    # Six-sample voxels that show at most two colours take four words instead of six
    # (format version 6, docs/FORMAT.md §10): the same samples, 8 bytes fewer each.
    # False writes every one in six words, as version 5 did, for comparisons.
    packed_voxels: bool = True
    # With quantized splits, treelets on 4-byte boundaries and LOD words in 4-byte units
    # (format version 7, docs/FORMAT.md §8): the 8-byte padding took 4-5 % of the node
    # levels. False writes version 6's layout, for comparisons and older-version tests.
    packed_treelets: bool = True
    # Blocks compressed with LZ4 HC at this level (1 ... 12) instead of LZ4's fast
    # compressor (0): the same block format, read as fast; at 9 the default layout's
    # files are 5-7 % smaller and 10^7 builds take 1.4-1.6x as long (docs/FORMAT.md,
    # "Measured choices", Compression).
    lz4_hc_level: int = 0
    # With quantized splits (only), each LOD node carries a bound on how far its voxel's box
    # surface lies from the triangles it stands in for (format version 8,
    # FLAG_VOXEL_ERRORS, docs/FORMAT.md §15), and its LOD test compares that instead of
    # the radius, never less than voxel_error_floor x the radius: a box around a thin
    # pipe stands in for it long before the box itself is small on screen. At the same
    # image accuracy the 10^8 plant's overview holds 0.61-0.85x the working set in the
    # same frame time, the 10^7 plant's views 0.68-1.09x (docs/FORMAT.md, "Measured
    # choices"); False keeps version 7's test, for comparisons.
    voxel_errors: bool = True
    voxel_error_floor: float = 0.5
    # Which way is up in the model: written into the header as a unit vector (bytes
    # 236-247, docs/FORMAT.md §2), so `vastray render` and a server that registers the
    # file frame it upright. None says nothing (readers take +y).
    up: tuple[float, float, float] | None = None

    def check(self) -> None:
        """Raises ValueError naming the first option that cannot work."""

        def number(name: str, kind: type) -> Any:
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, kind):
                what = "an integer" if kind is numbers.Integral else "a number"
                raise ValueError(f"{name} must be {what}, got {value!r}")
            return value

        if number("threads", numbers.Integral) < 0:
            raise ValueError(f"threads must be 0 (every core) or a positive count, got {self.threads}")
        if number("memory", numbers.Integral) < MIN_INCORE_TRIANGLES * INCORE_BYTES_PER_TRIANGLE:
            need = (MIN_INCORE_TRIANGLES * INCORE_BYTES_PER_TRIANGLE + (1 << 20) - 1) >> 20
            raise ValueError(f"memory budget too small: the builder needs at least {need} MiB")
        if number("leaf_size", numbers.Integral) < 1:
            raise ValueError(f"leaf_size must be at least 1, got {self.leaf_size}")
        if not 0 <= number("lz4_hc_level", numbers.Integral) <= 12:
            raise ValueError(f"lz4_hc_level must be 0 (fast LZ4) ... 12, got {self.lz4_hc_level}")
        if not 1 <= number("voxel_rays", numbers.Integral) <= 8:
            raise ValueError(f"voxel_rays must be 1 ... 8, got {self.voxel_rays}")
        if not 0 <= number("tier_width", numbers.Real) <= 16:
            raise ValueError(f"tier_width must be 0 (untiered) ... 16 octaves, got {self.tier_width!r}")
        if not 0 <= number("tier_coarse_octaves", numbers.Integral) <= 32:
            raise ValueError(f"tier_coarse_octaves must be 0 ... 32, got {self.tier_coarse_octaves}")
        for name in ("traversal_cost", "intersection_cost"):
            value = number(name, numbers.Real)
            if not (np.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be a positive number, got {value!r}")
        if not (0.0 <= number("empty_space_ratio", numbers.Real) < 1.0):
            raise ValueError(f"empty_space_ratio must be in [0, 1), got {self.empty_space_ratio!r}")
        if not (0.0 <= number("voxel_error_floor", numbers.Real) <= 1.0):
            raise ValueError(f"voxel_error_floor must be in [0, 1], got {self.voxel_error_floor!r}")
        if self.up is not None:
            unit_up(self.up)  # (its own clear error)

    def incore_limit(self) -> int:
        return max(MIN_INCORE_TRIANGLES, self.memory // INCORE_BYTES_PER_TRIANGLE)

    def writer_threads(self, largest_part: int) -> int:
        """The threads asked for (every core for 0), fewer where the largest in-core part
        would pass the budget on them; never fewer than 2, which the part sizes allow."""
        threads = self.threads or native.hardware_threads()
        while threads > 2 and incore_bytes_per_triangle(threads) * largest_part > self.memory:
            threads -= 1
        return threads

    def chunk(self) -> int:
        """Triangles per streaming chunk: a quarter of the budget at most."""
        return int(min(MAX_CHUNK, max(4096, self.memory // (4 * CHUNK_BYTES_PER_TRIANGLE))))


# ---- inputs ---------------------------------------------------------------------------------


@dataclass
class _Input:
    name: str
    has_colours: bool
    estimate: int  # triangles (exact when `exact`)
    exact: bool
    chunks: Callable[[int], Iterator[TriangleChunk]]  # triangles per chunk -> chunks
    rereadable: bool  # reading twice is cheap (files); generators are not
    vertices: VertexTable | None = None  # indexed input: records are gathered natively
    # Bounds of the input's vertices when known without a pass over its triangles
    # (indexed formats). The model centre is their midpoint, as in the in-core Scene.
    bounds: Callable[[], tuple[np.ndarray, np.ndarray] | None] = lambda: None
    parts: int = 0  # named parts in the input (counted once the triangles have been read)
    source: Any = None  # the TriangleSource, whose counts become exact once it is read


def _open_input(source: str | os.PathLike[str], scratch: Path, scan: Callable[[int, int], None]) -> _Input:
    from vastray import scenes
    from vastray.triangle_readers import open_triangles

    text = str(source)
    scene = parse_scene(text)
    if scene is not None:
        spec = scenes.SCENES[scene.name]

        def generated(_size: int = 0) -> Iterator[TriangleChunk]:
            first = 0
            for vertices, faces, colours in scenes.generate(scene.name, scene.triangles, scene.seed):
                parts = spec.part_of(colours) if spec.part_of is not None and colours is not None else None
                yield TriangleChunk(first, len(faces), corners=vertices[faces], colours=colours, parts=parts)
                first += len(faces)

        named = SimpleNamespace(parts=[PartName(object=name) for name in spec.part_names] or None)
        return _Input(scene.label, spec.coloured, scene.triangles, False, generated, False, source=named)

    path = Path(text)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such file (or use {SOURCE_HELP})")
    if is_model_file(path):
        raise ValueError(f"{path} is already a built model; build takes a mesh")
    stream = open_triangles(path, stage_dir=scratch, progress=scan)
    return _Input(
        path.stem,
        stream.has_colours,
        stream.triangle_count,
        stream.exact_count,
        stream.chunks,
        True,
        stream.vertices,
        stream.vertex_bounds,
        0,
        stream,
    )


def _input_part_names(src: _Input) -> list[str] | None:
    """The display name of each of the input's parts (after its triangles were read: an
    ASCII STL knows its solids only then), or None when it has none: no part list, or a
    single unnamed part (an OBJ without o, g or usemtl), as vastray.ingest decides."""
    parts = getattr(src.source, "parts", None)
    if not parts or (len(parts) == 1 and not (parts[0].object or parts[0].group or parts[0].material)):
        return None
    return [modelfile.part_name(p.object, p.group, p.material) for p in parts]


class _PartStats:
    """What the read pass learns of the input's parts: per part (the reader's index) the
    kept triangles and the bounds of their float32 local corners, and the runs of equal
    part over input triangle ids (docs/FORMAT.md §4a). Vectorised per chunk; a chunk
    without parts costs nothing."""

    def __init__(self) -> None:
        self.count = np.zeros(0, np.int64)
        self.lo = np.zeros((0, 3), np.float32)
        self.hi = np.zeros((0, 3), np.float32)
        self.firsts: list[np.ndarray] = []
        self.parts: list[np.ndarray] = []
        self.last_part = -2  # no run yet
        self.next_id = 0

    def _grow(self, n: int) -> None:
        if n > len(self.count):
            k = n - len(self.count)
            self.count = np.concatenate([self.count, np.zeros(k, np.int64)])
            self.lo = np.concatenate([self.lo, np.full((k, 3), np.inf, np.float32)])
            self.hi = np.concatenate([self.hi, np.full((k, 3), -np.inf, np.float32)])

    def _runs(self, ids: np.ndarray, p: np.ndarray) -> None:
        prev_next = np.empty_like(ids)
        prev_next[0] = self.next_id
        prev_next[1:] = ids[:-1] + 1
        if ids[0] < self.next_id or (len(ids) > 1 and (ids[1:] <= ids[:-1]).any()):
            raise RuntimeError("input triangle ids are not increasing")
        prev_p = np.empty_like(p)
        prev_p[0] = self.last_part
        prev_p[1:] = p[:-1]
        gap = ids != prev_next
        change = (p != prev_p) | gap
        first, part = ids[change], p[change]
        if gap.any():  # ids the input left out are in no part
            first = np.concatenate([first, prev_next[gap]])
            part = np.concatenate([part, np.full(int(gap.sum()), -1, np.int64)])
            order = np.argsort(first, kind="stable")
            first, part = first[order], part[order]
        self.last_part = int(p[-1])
        self.next_id = int(ids[-1]) + 1
        if len(part) == 0:  # the run goes on
            return
        before = np.empty_like(part)
        before[0] = prev_p[0]
        before[1:] = part[:-1]
        keep = part != before
        self.firsts.append(first[keep])
        self.parts.append(part[keep])

    def add(self, chunk: TriangleChunk, records: np.ndarray) -> None:
        """records: the chunk's kept records, a structured view with fields c and id."""
        if chunk.count == 0:
            return
        if chunk.parts is None and chunk.ids is None:
            # No part for these ids, nor for any the input skipped before them.
            if chunk.first < self.next_id:
                raise RuntimeError("input triangle ids are not increasing")
            if self.last_part != -1:
                self.firsts.append(np.array([self.next_id], np.int64))
                self.parts.append(np.array([-1], np.int64))
            self.last_part, self.next_id = -1, chunk.first + chunk.count
            return
        ids = chunk.triangle_ids.astype(np.int64)
        p = np.full(chunk.count, -1, np.int64) if chunk.parts is None else chunk.parts.astype(np.int64)
        self._runs(ids, p)
        if chunk.parts is None or len(records) == 0:
            return
        kept = records["id"].astype(np.int64)
        pos = kept - chunk.first if chunk.ids is None else np.searchsorted(ids, kept)
        pk = p[pos]
        # Per segment of equal part (few: parts are contiguous in most inputs), the
        # bounds of its nine corner coordinates, then of its three corners.
        starts = np.concatenate([[0], np.flatnonzero(pk[1:] != pk[:-1]) + 1])
        c = records["c"]
        if len(starts) > 64 and len(starts) > len(pk) // 64:
            # Interleaved parts (a PLY face property can be): group the records by part.
            order = np.argsort(pk, kind="stable")
            pk, c = pk[order], c[order]
            starts = np.concatenate([[0], np.flatnonzero(pk[1:] != pk[:-1]) + 1])
        seg_part = pk[starts]
        lo9 = np.minimum.reduceat(c, starts, axis=0)
        hi9 = np.maximum.reduceat(c, starts, axis=0)
        seg_lo = np.minimum(np.minimum(lo9[:, 0:3], lo9[:, 3:6]), lo9[:, 6:9])
        seg_hi = np.maximum(np.maximum(hi9[:, 0:3], hi9[:, 3:6]), hi9[:, 6:9])
        seg_n = np.diff(np.concatenate([starts, [len(pk)]]))
        named = seg_part >= 0
        if not named.any():
            return
        seg_part, seg_lo, seg_hi, seg_n = seg_part[named], seg_lo[named], seg_hi[named], seg_n[named]
        self._grow(int(seg_part.max()) + 1)
        if len(seg_part) == 1:
            k = int(seg_part[0])
            self.count[k] += int(seg_n[0])
            self.lo[k] = np.minimum(self.lo[k], seg_lo[0])
            self.hi[k] = np.maximum(self.hi[k], seg_hi[0])
        else:
            np.add.at(self.count, seg_part, seg_n)
            np.minimum.at(self.lo, seg_part, seg_lo)
            np.maximum.at(self.hi, seg_part, seg_hi)

    def table(self, names: list[str], centre: np.ndarray) -> modelfile.PartTable | None:
        """The parts section: parts with kept triangles, in order of first use, their
        bounds in world coordinates (centre + float32 local, in double)."""
        self._grow(len(names))
        firsts = np.concatenate(self.firsts) if self.firsts else np.zeros(1, np.int64)
        parts = np.concatenate(self.parts) if self.parts else np.full(1, -1, np.int64)
        if (parts >= len(names)).any():
            raise RuntimeError("a triangle's part is outside the input's part list")
        used = self.count[: len(names)] > 0
        if not used.any():
            return None
        first_run = np.full(len(names), len(parts), np.int64)
        named = parts >= 0
        np.minimum.at(first_run, parts[named], np.flatnonzero(named))
        order = [int(k) for k in np.argsort(first_run, kind="stable") if used[k]]
        new = np.full(len(names), -1, np.int64)
        new[order] = np.arange(len(order))
        parts = np.where(named, new[np.where(named, parts, 0)], -1)
        keep = np.concatenate([[True], parts[1:] != parts[:-1]])  # dropped parts join their neighbours
        return modelfile.PartTable(
            names=[names[k] for k in order],
            lo=centre[None, :] + self.lo[order].astype(np.float64),
            hi=centre[None, :] + self.hi[order].astype(np.float64),
            triangles=self.count[order],
            run_firsts=firsts[keep].astype(np.uint32),
            run_parts=parts[keep],
        )


def _record_dtype(colours: bool) -> np.dtype:
    fields: list[tuple[str, str] | tuple[str, str, tuple[int]]] = [("c", "<f4", (9,)), ("id", "<u4")]
    if colours:
        fields.append(("rgb", "<u4"))
    return np.dtype(fields)


# ---- the out-of-core part of the tree ----------------------------------------------------------


@dataclass
class _Part:
    """Triangles of one cell, small enough to build in core: records in a scratch file,
    or (when the whole input fits) in memory."""

    path: Path | None
    count: int
    lo: np.ndarray  # float32 cell
    hi: np.ndarray
    level: int
    records: np.ndarray | None = None  # (count, stride) uint8, when in memory


@dataclass
class _Split:
    """Three median-split levels (one treelet) over up to eight children."""

    lo: np.ndarray
    hi: np.ndarray
    level: int
    axes: list[int]
    splits: list[float]
    slot_lo: np.ndarray  # (8, 3) float32: the cells of the eight children
    slot_hi: np.ndarray
    lod_lo: np.ndarray  # (4, 3) float32: the cells of its LOD nodes, child slots 2j and 2j + 1's parent j
    lod_hi: np.ndarray
    children: list[_Part | _Split | None] = field(default_factory=list)


class _Sifter:
    """Sorts record chunks into the eight cells of a split, a scratch file per cell: a
    triangle goes to each cell whose closed half-spaces its bounding box touches.

    A thread of its own writes each chunk's cells while the caller makes and sifts the
    next chunk: at 10^8 triangles the writes are gigabytes, paced by the disk once the
    kernel's dirty-page limit is reached, and would otherwise stall everything else. At
    most one chunk waits for the writer, so the memory in flight stays two chunks."""

    def __init__(self, split: _Split, scratch: Path, stride: int) -> None:
        self.split, self.stride = split, stride
        self.paths = [scratch / f"n{id(split)}-{s}.tri" for s in range(8)]
        self.files = [open(p, "wb") for p in self.paths]
        self.counts = [0] * 8
        self.tlo = [np.full(3, np.inf, dtype=np.float32) for _ in range(8)]
        self.thi = [np.full(3, -np.inf, dtype=np.float32) for _ in range(8)]
        self._pending: queue.Queue[list[np.ndarray] | None] = queue.Queue(maxsize=1)
        self._error: BaseException | None = None
        self._writer: threading.Thread | None = threading.Thread(
            target=self._write_cells, name="vastray-sift-writer", daemon=True
        )
        self._writer.start()

    def _write_cells(self) -> None:
        # Keeps taking chunks after a failure, so that add() and close() never block on
        # a full queue; the first error is raised to the caller there.
        while (cells := self._pending.get()) is not None:
            if self._error is not None:
                continue
            k = 0
            try:
                for k, cell in enumerate(cells):
                    if len(cell):
                        # The file object's write: the GIL is let go during the system
                        # call, and a failure keeps its errno (numpy's tofile loses it).
                        self.files[k].write(memoryview(cell).cast("B"))
            except OSError as e:  # handed to the caller's thread
                self._error = self._scratch_error(e, k)
            except BaseException as e:
                self._error = e

    def _scratch_error(self, e: OSError, k: int) -> OSError:
        return OSError(e.errno, f"scratch write failed: {e.strerror}", str(self.paths[k]))

    def _raise_writer_error(self) -> None:
        if self._error is not None:
            error, self._error = self._error, None
            raise error

    def add(self, records: np.ndarray) -> None:
        """records: (n, stride) uint8."""
        self._raise_writer_error()
        s = self.split
        cells, bounds = native.sift8(records, s.axes, s.splits, s.slot_lo, s.slot_hi)
        for k, cell in enumerate(cells):
            if len(cell):
                self.counts[k] += len(cell)
                self.tlo[k] = np.minimum(self.tlo[k], bounds[k, :3])
                self.thi[k] = np.maximum(self.thi[k], bounds[k, 3:])
        self._pending.put(cells)

    def close(self) -> None:
        """Waits for the writes, closes the files; raises what the writer met. Safe to
        call again."""
        if self._writer is not None:
            self._pending.put(None)
            self._writer.join()
            self._writer = None
        for k, f in enumerate(self.files):
            try:
                f.close()  # writes what is still buffered
            except OSError as e:
                if self._error is None:
                    self._error = self._scratch_error(e, k)
        self._raise_writer_error()

    def finish(self) -> list[tuple[Path, int, np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None]:
        """Per cell (path, count, cell lo, cell hi, triangles' lo, hi), or None if empty."""
        self.close()
        out: list[tuple[Path, int, np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None] = []
        for k in range(8):
            if self.counts[k] == 0:
                self.paths[k].unlink(missing_ok=True)
                out.append(None)
            else:
                s = self.split
                out.append(
                    (self.paths[k], self.counts[k], s.slot_lo[k], s.slot_hi[k], self.tlo[k], self.thi[k])
                )
        return out


class _Records:
    """Where the read pass puts its records: in memory while the input fits one in-core
    part (the native record maker writes them in place), then (and from the start, when
    the input is known to be bigger) sifted into the first out-of-core treelet's cells."""

    def __init__(self, stride: int, limit: int, expected: int, split: Callable[[], _Sifter]) -> None:
        self.stride, self.limit, self.make_sifter = stride, limit, split
        self.sifter: _Sifter | None = None
        self.count = 0
        self.buffer = np.empty((min(expected, limit) if expected <= limit else 0, stride), np.uint8)
        if expected > limit:
            self.sifter = split()

    def space(self, n: int) -> np.ndarray | None:
        """Room for the records of n more triangles, or None when they are to be sifted."""
        if self.sifter is None and self.count + n > self.limit:
            self.sifter = self.make_sifter()
            if self.count:
                self.sifter.add(self.buffer[: self.count])
            self.buffer = np.empty((0, self.stride), np.uint8)
        if self.sifter is not None:
            return None
        if self.count + n > len(self.buffer):
            # Room for the whole in-core part at once: pages become resident only as
            # records are written, while growing by copies cost more than the native
            # record maker (each copy also faults in fresh pages; 1.2 s of a 1.6 s read
            # phase at 10^7). A budget beyond what the system will map grows as it goes.
            try:
                grown = np.empty((self.limit, self.stride), np.uint8)
            except MemoryError:
                rows = min(self.limit, max(self.count + n, len(self.buffer) * 3 // 2))
                grown = np.empty((rows, self.stride), np.uint8)
            grown[: self.count] = self.buffer[: self.count]
            self.buffer = grown
        return self.buffer[self.count : self.count + n]

    def commit(self, records: np.ndarray) -> None:
        """Takes the records made in `space()` (or, when sifting, anywhere)."""
        if self.sifter is not None:
            self.sifter.add(records)
        self.count += len(records)

    def in_memory(self) -> np.ndarray:
        return self.buffer[: self.count]


class _Builder:
    def __init__(
        self,
        output: Path,
        options: BuildOptions,
        progress: Callable[[BuildProgress], None] | None,
        cancel: threading.Event | None,
    ) -> None:
        self.output = output
        self.opt = options
        self.progress_cb = progress
        self.cancel = cancel
        self.start = time.perf_counter()
        self.phase_seconds: dict[str, float] = {}
        self.warnings: list[str] = []
        self.sifted = 0
        self.sift_estimate = 1

    # -- plumbing ---------------------------------------------------------------------------

    def report(self, phase: str, done: int, total: int, unit: str = "triangles", message: str = "") -> None:
        if self.cancel is not None and self.cancel.is_set():
            raise BuildCancelledError("build cancelled")
        if self.progress_cb is not None:
            self.progress_cb(
                BuildProgress(phase, done, total, unit, time.perf_counter() - self.start, message)
            )

    def timed(self, phase: str, since: float) -> float:
        now = time.perf_counter()
        self.phase_seconds[phase] = self.phase_seconds.get(phase, 0.0) + now - since
        return now

    # -- phase 1: scan ----------------------------------------------------------------------

    def open(self, source: str | os.PathLike[str], scratch: Path) -> None:
        self.src = _open_input(source, scratch, lambda done, total: self.report("scan", done, total, "bytes"))
        self.dtype = _record_dtype(self.src.has_colours)

    def bounds(
        self, scratch: Path
    ) -> tuple[np.ndarray, np.ndarray, Callable[[int], Iterator[TriangleChunk]]]:
        """The input's bounds in double, and how to read its triangles for the records."""
        known = self.src.bounds() if self.src.rereadable else None
        if known is not None:
            return known[0], known[1], self.src.chunks
        lo = np.full(3, np.inf)
        hi = np.full(3, -np.inf)
        total = 0
        if self.src.rereadable:
            for chunk in self.src.chunks(self.opt.chunk()):
                corners = chunk.corners
                lo = np.minimum(lo, corners.min(axis=(0, 1)))
                hi = np.maximum(hi, corners.max(axis=(0, 1)))
                total += chunk.count
                self.report("scan", total, max(total, self.src.estimate), message="bounds")
            self.report("scan", total, total, message="bounds")
            return lo, hi, self.src.chunks
        # A generator runs once and the centre is known only at its end: stage the
        # corners in double, so the records get exactly float32(vertex - centre), as
        # files and the in-core Scene do (float32 relative to a provisional origin
        # would round twice).
        staged: list[tuple[str, str] | tuple[str, str, tuple[int]]] = [("c", "<f8", (9,))]
        if self.src.has_colours:
            staged.append(("rgb", "u1", (3,)))
        has_parts = bool(getattr(self.src.source, "parts", None))
        if has_parts:
            staged.append(("part", "<u4"))
        dtype = np.dtype(staged)
        path = scratch / "input.f64"
        with open(path, "wb") as f:
            for chunk in self.src.chunks(self.opt.chunk()):
                corners = chunk.corners
                lo = np.minimum(lo, corners.min(axis=(0, 1)))
                hi = np.maximum(hi, corners.max(axis=(0, 1)))
                rec = np.empty(chunk.count, dtype)
                rec["c"] = corners.reshape(-1, 9)
                if chunk.colours is not None:
                    rec["rgb"] = chunk.colours
                if has_parts:
                    rec["part"] = chunk.parts
                rec.tofile(f)
                total += chunk.count
                self.report("scan", total, max(total, self.src.estimate), message="generating")
        self.report("scan", total, total, message="generating")
        self.src.estimate, self.src.exact = total, True

        def staged_chunks(size: int) -> Iterator[TriangleChunk]:
            first = 0
            for rec in _read_records(path, dtype, size):
                colours = rec["rgb"] if self.src.has_colours else None
                parts = rec["part"] if has_parts else None
                yield TriangleChunk(
                    first, len(rec), corners=rec["c"].reshape(-1, 3, 3), colours=colours, parts=parts
                )
                first += len(rec)
            path.unlink()

        return lo, hi, staged_chunks

    # -- phase 2: read ----------------------------------------------------------------------

    def read(
        self, scratch: Path, lo: np.ndarray, hi: np.ndarray, chunks: Callable[[int], Iterator[TriangleChunk]]
    ) -> tuple[_Records, _Split | None, int, int, np.ndarray, np.ndarray, np.ndarray]:
        """Returns (records, the first split or None, kept count, input count, centre,
        lo, hi): lo/hi is the cell of the kept records (their bounds when they stay in
        memory; else the conservative bounds the first split was made in)."""
        if not np.isfinite(lo).all():
            raise MeshError(f"{self.src.name}: the input has no triangles")
        centre = 0.5 * (lo + hi)
        # Rounding to nearest is monotonic, so float32(v - centre) stays in this box.
        cell_lo = (lo - centre).astype(np.float32)
        cell_hi = (hi - centre).astype(np.float32)
        limit = self.opt.incore_limit()
        first_split: list[_Split] = []

        def sifter() -> _Sifter:
            split = _choose_splits(cell_lo, cell_hi, cell_lo, cell_hi, 0, self.opt.quantized_splits)
            first_split.append(split)
            return _Sifter(split, scratch, self.dtype.itemsize)

        expected = self.src.estimate if self.src.exact else 0
        records = _Records(self.dtype.itemsize, limit, expected, sifter)
        total = 0
        box_lo = np.full(3, np.inf, dtype=np.float32)
        box_hi = np.full(3, -np.inf, dtype=np.float32)
        table = self.src.vertices
        table_bytes = table.buffer() if table is not None else None
        centre_list = centre.tolist()
        self.part_stats = _PartStats()
        try:
            for chunk in chunks(self.opt.chunk()):
                ids = None if chunk.ids is None else chunk.ids.astype(np.uint32)
                if chunk.first + chunk.count > MAX_INPUT_TRIANGLES:
                    raise ValueError(f"{self.src.name}: over {MAX_INPUT_TRIANGLES} triangles; ids are 32-bit")
                out = records.space(chunk.count)
                if chunk.indices is not None and table is not None:
                    # Native: gathers each corner from the vertex records, then records as below.
                    if table_bytes is None:
                        table_bytes = table.buffer()
                    rec, _, lo_k, hi_k, bad = native.make_indexed_records(
                        table_bytes, table.stride, table.offsets, table.types, table.count,
                        chunk.indices, chunk.colours, ids, chunk.first, centre_list, out, self.opt.threads,
                    )  # fmt: skip
                    if bad >= 0:
                        idx = np.asarray(chunk.indices[bad], dtype=np.int64)
                        j = int(idx[(idx < 0) | (idx >= table.count)][0])
                        raise MeshError(
                            f"{self.src.name}: face {chunk.first + bad} refers to vertex {j}, "
                            f"but there are only {table.count} vertices"
                        )
                else:
                    # Native: float32(vertex - centre) computed in double, as in the in-core
                    # Scene (bit-identical vertices on both paths); zero-area triangles (in
                    # those float32 coordinates) are left out and counted.
                    rec, _, lo_k, hi_k, _ = native.make_records(
                        chunk.corners, chunk.colours, ids, chunk.first, centre_list, out, self.opt.threads
                    )
                if self.opt.quantized_vertices:
                    native.snap_to_vertex_grid(rec, cell_lo.tolist(), cell_hi.tolist())
                self.part_stats.add(chunk, rec.view(self.dtype).reshape(-1))
                if len(rec):
                    box_lo = np.minimum(box_lo, np.asarray(lo_k, dtype=np.float32))
                    box_hi = np.maximum(box_hi, np.asarray(hi_k, dtype=np.float32))
                    records.commit(rec)
                total = max(total, chunk.first + chunk.count)
                self.report("read", total, max(total, self.src.estimate))
                # Vertices read at random leave the resident set with their map.
                table_bytes = None
        finally:
            if records.sifter is not None:
                records.sifter.close()
        self.report("read", total, total)
        if total == 0:
            raise MeshError(f"{self.src.name}: the input has no triangles")
        if records.count == 0:
            raise MeshError(f"{self.src.name}: all {total} triangles are degenerate (zero area)")
        if records.sifter is None:
            # In core the root cell is the kept triangles' box, unless the vertex grid was
            # made from the input's cell: a reader derives the grid from the header's.
            lo, hi = (cell_lo, cell_hi) if self.opt.quantized_vertices else (box_lo, box_hi)
            return records, None, records.count, total, centre, lo, hi
        return records, first_split[0], records.count, total, centre, cell_lo, cell_hi

    # -- phase 3: split ---------------------------------------------------------------------

    def plan(
        self,
        path: Path,
        count: int,
        lo: np.ndarray,
        hi: np.ndarray,
        tight_lo: np.ndarray,
        tight_hi: np.ndarray,
        level: int,
        limit: int,
    ) -> _Part | _Split:
        if count <= limit:
            return _Part(path, count, lo, hi, level)
        if level >= MAX_OUT_OF_CORE_LEVELS:
            self.warnings.append(f"out-of-core splitting stopped at level {level} with {count:,} triangles")
            return _Part(path, count, lo, hi, level)
        split = _choose_splits(lo, hi, tight_lo, tight_hi, level, self.opt.quantized_splits)
        sifter = _Sifter(split, self.scratch, self.dtype.itemsize)
        try:
            for rec in _read_records(path, self.dtype, self.opt.chunk()):
                sifter.add(rec.view(np.uint8).reshape(len(rec), self.dtype.itemsize))
                self.sifted += len(rec)
                self.report(
                    "split", self.sifted, max(self.sifted, self.sift_estimate), message=f"level {level}"
                )
        finally:
            sifter.close()
        path.unlink()
        self.adopt(split, sifter.finish(), count, level, limit)
        return split

    def adopt(self, split: _Split, kids: list[Any], count: int, level: int, limit: int) -> None:
        """Plans the children of a sifted split."""
        for kid in kids:
            if kid is None:
                split.children.append(None)
                continue
            kpath, kcount, clo, chi, tlo, thi = kid
            if kcount > 0.95 * count:
                # Splitting no longer separates these triangles (huge or coincident ones):
                # build them in core rather than split forever.
                self.warnings.append(f"{kcount:,} triangles in one cell could not be split further")
                split.children.append(_Part(kpath, kcount, clo, chi, level + 1))
            else:
                split.children.append(self.plan(kpath, kcount, clo, chi, tlo, thi, level + 1, limit))

    # -- phase 4: build ---------------------------------------------------------------------

    def emit(
        self,
        node: _Part | _Split,
        writer: native.ModelWriter,
        lod_parent: tuple[list[float], list[float]] | None = None,
    ) -> int:
        """Hands a subtree to the writer, bottom-up; `lod_parent` is the cell of the LOD
        node above it (None at the root), whose radius tiers the leaves of a part's root
        treelet (the writer knows it for everything deeper)."""
        if isinstance(node, _Split):
            handles = [
                self.emit(k, writer, (node.lod_lo[i // 2].tolist(), node.lod_hi[i // 2].tolist()))
                if k is not None
                else -1
                for i, k in enumerate(node.children)
            ]
            return writer.add_inner_treelet(
                node.level, node.lo.tolist(), node.hi.tolist(), node.axes, node.splits, handles
            )
        if node.records is not None:
            recs, node.records = node.records, None
        else:
            assert node.path is not None
            recs = _map_records(node.path, self.dtype.itemsize)
            node.path.unlink()  # its pages stay until the map goes
        self.part_base = self.built
        self.part_refs0 = self.refs_seen
        self.part_count = node.count
        handle = writer.add_subtree(recs, node.lo.tolist(), node.hi.tolist(), node.level, lod_parent)
        del recs
        part_refs = self.refs_seen - self.part_refs0
        if node.count:
            self.dup = max(1.0, part_refs / node.count)
        self.built += node.count
        self.report("build", self.built, self.build_total)
        return handle

    def on_refs(self, refs: int) -> None:
        self.refs_seen = refs
        within = min(self.part_count, int((refs - self.part_refs0) / self.dup))
        self.report("build", self.part_base + within, self.build_total)

    # -- all phases -------------------------------------------------------------------------

    def run(self, source: str | os.PathLike[str], scratch: Path, partial: Path) -> dict[str, Any]:
        self.scratch = scratch
        t = time.perf_counter()
        self.open(source, scratch)
        lo, hi, chunks = self.bounds(scratch)
        t = self.timed("scan", t)
        records, first_split, count, total, centre, lo, hi = self.read(scratch, lo, hi, chunks)
        names = _input_part_names(self.src)
        part_table = self.part_stats.table(names, centre) if names is not None else None
        self.src.parts = sum(1 for n in names if n != "(unnamed)") if names is not None else 0
        del self.part_stats
        t = self.timed("read", t)

        limit = self.opt.incore_limit()
        if first_split is None:
            tree: _Part | _Split = _Part(None, count, lo, hi, 0, records.in_memory())
        else:
            # Each further out-of-core level passes over every triangle once (plus duplicates).
            levels_needed = 0
            n = count // 8
            while n > limit:
                n //= 8
                levels_needed += 1
            self.sift_estimate = max(1, count * levels_needed)
            assert records.sifter is not None
            self.adopt(first_split, records.sifter.finish(), count, 0, limit)
            tree = first_split
        del records
        t = self.timed("split", t)

        parts = list(_parts(tree))
        self.build_total = sum(p.count for p in parts)
        self.built = 0
        self.refs_seen = 0
        self.part_base = self.part_refs0 = self.part_count = 0
        self.dup = 1.5
        steps = native.vertex_grid_steps(lo.tolist(), hi.tolist()) if self.opt.quantized_vertices else None
        self.threads_used = self.opt.writer_threads(max((p.count for p in parts), default=0))
        voxel_errors = self.opt.voxel_errors and self.opt.quantized_splits  # only with quantized splits
        writer = native.ModelWriter(
            has_colours=self.src.has_colours,
            # Every block goes into the model file as it is made (model_assembly.py).
            output=str(partial),
            output_offset=model_assembly.front_reserve(count),
            progress=self.on_refs,
            leaf_size=self.opt.leaf_size,
            traversal_cost=self.opt.traversal_cost,
            intersection_cost=self.opt.intersection_cost,
            empty_space_ratio=self.opt.empty_space_ratio,
            voxel_rays=self.opt.voxel_rays,
            threads=self.threads_used,
            quantized_splits=self.opt.quantized_splits,
            vertex_steps=steps,
            tier_width=self.opt.tier_width,
            tier_coarse_octaves=self.opt.tier_coarse_octaves,
            root_cell=(lo.tolist(), hi.tolist()),
            compact_triangles=self.opt.compact_triangles,
            packed_voxels=self.opt.packed_voxels,
            packed_treelets=self.opt.packed_treelets,
            lz4_hc_level=self.opt.lz4_hc_level,
            voxel_errors=voxel_errors,
            voxel_error_floor=self.opt.voxel_error_floor,
        )
        self.report("build", 0, self.build_total)
        root_handle = self.emit(tree, writer)
        writer.finish(root_handle)
        stats = writer.stats
        # {level: ((n, 5) stored size, raw size, crc32, codec, tier; (n,) offsets)}
        levels = writer.levels
        blocks_at = writer.output  # (partial, start, end, direct): where the blocks are
        t = self.timed("build", t)

        layout = model_assembly.assemble_streams(stats, levels, self.opt.tier_width > 0)
        entries = layout.entries
        node_levels = len(stats["node_streams"])
        stored_total = sum(e[0] for e in entries)
        packed_treelets = self.opt.quantized_splits and self.opt.packed_treelets  # only with quantized splits
        fields = {
            "flags": modelfile.FLAG_TRIANGLE_IDS
            | (modelfile.FLAG_COLOURS if self.src.has_colours else 0)
            | (modelfile.FLAG_QUANTIZED_SPLITS if self.opt.quantized_splits else 0)
            | (modelfile.FLAG_QUANTIZED_VERTICES if self.opt.quantized_vertices else 0)
            | (modelfile.FLAG_COMPACT_TRIANGLES if self.opt.compact_triangles else 0)
            | (modelfile.FLAG_PACKED_TREELETS if packed_treelets else 0)
            | (modelfile.FLAG_VOXEL_ERRORS if voxel_errors else 0),
            "centre": tuple(float(x) for x in centre),
            "cell_lo": tuple(float(x) for x in lo),
            "cell_hi": tuple(float(x) for x in hi),
            "triangle_count": count,
            "input_triangles": total,
            "degenerate": total - count + stats["degenerate"],
            "basic_nodes": stats["basic_nodes"],
            "lod_nodes": stats["lod_nodes"],
            "leaves": stats["leaves"],
            "voxels_one": stats["voxels_one"],
            "voxels_six": stats["voxels_six"],
            "voxels_packed": stats["voxels_packed"],
            "references": stats["references"],
            "up": unit_up(self.opt.up) if self.opt.up is not None else (0.0, 0.0, 0.0),
        }
        size, in_place = model_assembly.write_model(
            partial,
            fields,
            layout,
            part_table,
            blocks_at,
            lambda done, total: self.report("write", done, total, unit="bytes"),
        )
        t = self.timed("write", t)

        raw_total = sum(e[1] for e in entries)
        return {
            "input": self.src.name,
            "output": str(self.output),
            "triangles": count,
            "input_triangles": total,
            "degenerate": total - count,
            "input_parts": self.src.parts,
            "file_bytes": size,
            "raw_bytes": raw_total,
            "compression_ratio": raw_total / stored_total if stored_total else 1.0,
            "bytes_per_triangle": size / count,
            "node_levels": node_levels,
            "blocks": len(entries),
            "parts": len(part_table.names) if part_table is not None else 0,
            "incore_parts": len(parts),
            "out_of_core_levels": _depth(tree),
            "incore_limit": limit,
            "writer_threads": self.threads_used,
            "seconds": time.perf_counter() - self.start,
            "phase_seconds": dict(self.phase_seconds),
            "triangles_per_second": count / max(1e-9, time.perf_counter() - self.start),
            "peak_rss_bytes": peak_rss_bytes(),
            "warnings": self.warnings,
            **{k: stats[k] for k in ("basic_nodes", "lod_nodes", "leaves", "voxels_one", "voxels_six",
                                     "voxels_packed", "references", "stored_triangles", "stored_vertices",
                                     "vertex_bytes", "kd_build_ms", "emit_ms", "max_depth", "emission_jobs",
                                     "lod_errors_below_radius", "voxel_error_ms")},
            "lod_error_ratio": stats["lod_error_ratio_sum"] / max(1, stats["lod_nodes"]),
            "tiers": layout.tier_count,
            "blocks_in_place": in_place,
        }  # fmt: skip


def peak_rss_bytes() -> int:
    """This process's peak resident memory. Linux's VmHWM belongs to the process's own
    address space; ru_maxrss also carries the peak of a parent it was forked from (a
    server, a notebook), so it is only the fallback."""
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024


def _map_records(path: Path, itemsize: int) -> np.ndarray:
    """A part's scratch file as (n, itemsize) records, mapped rather than read: a read
    copied the 10^8 plant's parts (600 MiB each) into fresh memory that the kernel had to
    clear first, about a second a part with the other core idle. The map holds the page
    cache's own pages; the build reads all of them, so they count in the resident set
    much as the copy did, and go with the array."""
    with open(path, "rb") as f:
        if os.fstat(f.fileno()).st_size == 0:
            return np.empty((0, itemsize), np.uint8)
        # MAP_POPULATE: map every page now, in one call, not at a fault each.
        flags = mmap.MAP_SHARED | getattr(mmap, "MAP_POPULATE", 0)
        mapped = mmap.mmap(f.fileno(), 0, flags=flags, prot=mmap.PROT_READ)
    return np.frombuffer(mapped, dtype=np.uint8).reshape(-1, itemsize)


def _read_records(path: Path, dtype: np.dtype, chunk: int) -> Iterator[np.ndarray]:
    """Sequential chunks of a scratch file. Plain reads, not a memory map: pages already
    processed must not stay in the resident set, which the budget is measured on."""
    with open(path, "rb") as f:
        while len(rec := np.fromfile(f, dtype=dtype, count=chunk)):
            yield rec


def _choose_splits(
    lo: np.ndarray,
    hi: np.ndarray,
    tight_lo: np.ndarray,
    tight_hi: np.ndarray,
    level: int,
    quantized: bool = False,
) -> _Split:
    """Median splits for three levels, in heap order: each halves the longest side of
    the occupied part of its cell, so empty space is cut away as it goes. `quantized`:
    each split is the nearest plane of its cell's grid (FLAG_QUANTIZED_SPLITS)."""
    axes: list[int] = []
    splits: list[float] = []
    boxes = {0: (np.maximum(lo, tight_lo), np.minimum(hi, tight_hi))}
    cells = {0: (lo.astype(np.float32), hi.astype(np.float32))}
    for h in range(7):
        clo, chi = cells[h]
        blo, bhi = boxes[h]
        ext = bhi - blo
        axis = int(np.argmax(ext))
        value = np.float32(0.5 * (float(blo[axis]) + float(bhi[axis])))
        if quantized and ext[axis] > 0:
            snapped = modelfile.quantize_split(clo[axis], chi[axis], value)
            value = np.float32(snapped) if snapped is not None else np.float32(np.nan)
        if not (ext[axis] > 0 and clo[axis] < value < chi[axis]):
            axis = int(np.argmax(chi - clo))
            value = np.float32(0.5 * (float(clo[axis]) + float(chi[axis])))
            if quantized:
                snapped = modelfile.quantize_split(clo[axis], chi[axis], value)
                if snapped is None:
                    raise ValueError(f"an out-of-core cell too narrow to split: {clo} .. {chi}")
                value = np.float32(snapped)
        axes.append(axis)
        splits.append(float(value))
        for side, child in ((0, 2 * h + 1), (1, 2 * h + 2)):
            c_lo, c_hi = clo.copy(), chi.copy()
            if side == 0:
                c_hi[axis] = value
            else:
                c_lo[axis] = value
            cells[child] = (c_lo, c_hi)
            boxes[child] = (np.maximum(blo, c_lo), np.minimum(bhi, c_hi))
    slot_lo = np.array([cells[7 + s][0] for s in range(8)], dtype=np.float32)
    slot_hi = np.array([cells[7 + s][1] for s in range(8)], dtype=np.float32)
    lod_lo = np.array([cells[3 + j][0] for j in range(4)], dtype=np.float32)
    lod_hi = np.array([cells[3 + j][1] for j in range(4)], dtype=np.float32)
    return _Split(
        lo.astype(np.float32), hi.astype(np.float32), level, axes, splits, slot_lo, slot_hi, lod_lo, lod_hi
    )


def _parts(node: _Part | _Split | None) -> Iterator[_Part]:
    if isinstance(node, _Part):
        yield node
    elif isinstance(node, _Split):
        for k in node.children:
            yield from _parts(k)


def _depth(node: _Part | _Split | None) -> int:
    if isinstance(node, _Split):
        return 1 + max(_depth(k) for k in node.children)
    return 0


def build_model(
    source: str | os.PathLike[str],
    output: str | os.PathLike[str],
    options: BuildOptions | None = None,
    *,
    progress: Callable[[BuildProgress], None] | None = None,
    cancel: threading.Event | None = None,
) -> dict[str, Any]:
    """Builds `source` (a mesh file, 'demo' or 'scene:NAME:TRIANGLES:SEED') into the
    model file `output`; returns a report of counts, sizes and timings: the input's
    triangles as the file holds them (`input_triangles`), the degenerate ones dropped
    (`degenerate`) and those built (`triangles`)."""
    opt = options or BuildOptions()
    opt.check()
    out = Path(output)
    if out.exists() and not opt.overwrite:
        raise FileExistsError(f"{out} exists; pass overwrite (--force) to replace it")
    if not out.parent.is_dir():
        raise FileNotFoundError(f"{out.parent}: no such directory for the output")
    if parse_scene(str(source)) is None and not Path(source).is_file():
        raise FileNotFoundError(f"{source}: no such file (or use {SOURCE_HELP})")
    scratch = Path(tempfile.mkdtemp(prefix=".vastray-build-", dir=opt.scratch_dir or out.parent))
    partial = out.with_name(f".{out.name}.partial-{os.getpid()}")
    builder = _Builder(out, opt, progress, cancel)
    try:
        report = builder.run(source, scratch, partial)
        if cancel is not None and cancel.is_set():  # the last chance: nothing is in place yet
            raise BuildCancelledError("build cancelled")
        if out.exists() and not opt.overwrite:
            raise FileExistsError(f"{out} appeared during the build; not replacing it")
        os.replace(partial, out)
        return report
    finally:
        partial.unlink(missing_ok=True)
        shutil.rmtree(scratch, ignore_errors=True)
