"""Builds the out-of-core model from any triangle input within a memory budget
(paper 000 §4; the file format is in docs/FORMAT.md).

Phases, each reported through `progress`:
1. read   Stream the input once, write its triangles as model-local float32 records
          (relative to the model centre, which is kept in double) to a scratch file,
          and drop zero-area triangles.
2. split  While a node's triangles exceed what the budget lets us build in core, split
          it out of core: one pass over its scratch file sifts the triangles into the
          eight cells of three median-split levels (a whole treelet). Straddling
          triangles go to every cell they touch.
3. build  Each part that fits is loaded and handed to the native writer, which builds
          its kd-tree with binned SAH and empty-space cutting on all cores, samples the
          LOD voxels, and emits treelets and triangle blocks. The out-of-core treelets
          above the parts are then written bottom-up.
4. write  Blocks are LZ4-compressed and checksummed as they are produced, kept in one
          scratch file per LOD level, and finally assembled behind the header and the
          block index into a temporary file that is renamed over the output.
Nothing is left behind on failure, cancellation or Ctrl-C: scratch files and the
temporary output are removed.
"""

from __future__ import annotations

import os
import resource
import shutil
import tempfile
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from vastray import modelfile, native
from vastray.mesh import MeshError
from vastray.sources import SOURCE_HELP, is_model_file, parse_scene

# Peak memory of an in-core part per triangle, measured with bench/build.py (peak RSS
# growth while add_subtree() runs, plus the loaded records): kd-tree references,
# clipping buffers, nodes and the writer's pending treelets. Parts are sized with it.
INCORE_BYTES_PER_TRIANGLE = 240
# The budget covers the builder's working set: streaming chunks and in-core parts. On
# top of it comes a fixed overhead that does not grow with the model: the interpreter,
# numpy, trimesh, lz4 and the native module (90 MiB measured) plus allocator slack.
STATED_OVERHEAD_BYTES = 128 << 20
# Streaming passes hold a chunk of records plus its float64 corners, bounds and masks.
CHUNK_BYTES_PER_TRIANGLE = 300
MAX_CHUNK = 1 << 19
MIN_INCORE_TRIANGLES = 20_000
MAX_OUT_OF_CORE_LEVELS = 16
DEFAULT_MEMORY = 2 << 30


class BuildCancelledError(Exception):
    """The build was cancelled through its cancel event; nothing was written."""


@dataclass
class BuildProgress:
    phase: str  # read, split, build, write
    done: int
    total: int
    unit: str  # what done/total count: triangles or bytes
    elapsed: float  # seconds since the build started
    message: str = ""


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

    def incore_limit(self) -> int:
        return max(MIN_INCORE_TRIANGLES, self.memory // INCORE_BYTES_PER_TRIANGLE)

    def chunk(self) -> int:
        """Triangles per streaming chunk: a quarter of the budget at most."""
        return int(min(MAX_CHUNK, max(4096, self.memory // (4 * CHUNK_BYTES_PER_TRIANGLE))))


# ---- inputs ---------------------------------------------------------------------------------


@dataclass
class _Input:
    name: str
    has_colours: bool
    estimate: int  # triangle count for progress (exact for files)
    chunks: Callable[[], Iterator[tuple[np.ndarray, np.ndarray | None]]]
    rereadable: bool  # reading twice is cheap (files, meshes); generators are not
    # Bounds of the input's vertices when known without a pass over its triangles
    # (indexed formats). The model centre is their midpoint, as in the in-core Scene.
    bounds: Callable[[], tuple[np.ndarray, np.ndarray] | None] = lambda: None


def _open_input(source: str | os.PathLike[str], chunk: int) -> _Input:
    from vastray import scenes
    from vastray.triangle_readers import open_triangles

    text = str(source)
    scene = parse_scene(text)
    if scene is not None:

        def generated() -> Iterator[tuple[np.ndarray, np.ndarray | None]]:
            for vertices, faces, colours in scenes.generate(scene.name, scene.triangles, scene.seed):
                yield vertices[faces], colours

        return _Input(scene.label, scenes.SCENES[scene.name].coloured, scene.triangles, generated, False)

    path = Path(text)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such file (or use {SOURCE_HELP})")
    if is_model_file(path):
        raise ValueError(f"{path} is already a built model; build takes a mesh")
    try:
        stream = open_triangles(path)
    except MeshError:
        stream = None  # ASCII PLY/STL or another format: load it whole through trimesh
    if stream is not None:

        def streamed() -> Iterator[tuple[np.ndarray, np.ndarray | None]]:
            for part in stream.chunks(chunk):
                yield part.corners, part.colours

        return _Input(
            path.stem, stream.has_colours, stream.triangle_count, streamed, True, stream.vertex_bounds
        )

    from vastray.ingest import load_mesh

    mesh = load_mesh(path)

    def loaded() -> Iterator[tuple[np.ndarray, np.ndarray | None]]:
        for first in range(0, mesh.triangle_count, chunk):
            faces = mesh.faces[first : first + chunk]
            colours = None if mesh.face_colours is None else mesh.face_colours[first : first + chunk]
            yield mesh.vertices[faces], colours

    return _Input(
        path.stem,
        mesh.face_colours is not None,
        mesh.triangle_count,
        loaded,
        True,
        lambda: (mesh.vertices.min(axis=0), mesh.vertices.max(axis=0)),
    )


def _record_dtype(colours: bool) -> np.dtype:
    fields: list[tuple[str, str] | tuple[str, str, tuple[int]]] = [("c", "<f4", (9,)), ("id", "<u4")]
    if colours:
        fields.append(("rgb", "<u4"))
    return np.dtype(fields)


# ---- the out-of-core part of the tree ----------------------------------------------------------


@dataclass
class _Part:
    """Triangles of one cell in a scratch file, small enough to build in core."""

    path: Path
    count: int
    lo: np.ndarray  # float32 cell
    hi: np.ndarray
    level: int


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
    children: list[_Part | _Split | None] = field(default_factory=list)


class _Builder:
    def __init__(
        self,
        source: _Input,
        output: Path,
        options: BuildOptions,
        progress: Callable[[BuildProgress], None] | None,
        cancel: threading.Event | None,
    ) -> None:
        self.src = source
        self.output = output
        self.opt = options
        self.progress_cb = progress
        self.cancel = cancel
        self.start = time.perf_counter()
        self.dtype = _record_dtype(source.has_colours)
        # A generator's triangles as they came, in input order (ids follow from position).
        staged: list[tuple[str, str, tuple[int]]] = [("c", "<f8", (9,))]
        if source.has_colours:
            staged.append(("rgb", "u1", (3,)))
        self.staged_dtype = np.dtype(staged)
        self.phase_seconds: dict[str, float] = {}
        self.warnings: list[str] = []

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

    # -- phase 1: read ----------------------------------------------------------------------

    def read(self, scratch: Path) -> tuple[Path, int, int, int, np.ndarray, np.ndarray, np.ndarray]:
        """Writes root records; returns (path, count, input count, degenerate, centre, lo, hi)."""
        total = 0
        lo = np.full(3, np.inf)
        hi = np.full(3, -np.inf)
        staged = scratch / "input.f32"
        known = self.src.bounds() if self.src.rereadable else None
        if known is not None:
            lo, hi = known
            total = self.src.estimate
        elif self.src.rereadable:
            for corners, _ in self.src.chunks():
                lo = np.minimum(lo, corners.min(axis=(0, 1)))
                hi = np.maximum(hi, corners.max(axis=(0, 1)))
                total += len(corners)
                self.report("read", total, 2 * self.src.estimate, message="bounds")
        else:
            # A generator runs once and the centre is known only at its end: stage the
            # corners in double, so the records get exactly float32(vertex - centre), as
            # files and the in-core Scene do (float32 relative to a provisional origin
            # would round twice).
            with open(staged, "wb") as f:
                for corners, colours in self.src.chunks():
                    lo = np.minimum(lo, corners.min(axis=(0, 1)))
                    hi = np.maximum(hi, corners.max(axis=(0, 1)))
                    rec = np.empty(len(corners), self.staged_dtype)
                    rec["c"] = corners.reshape(-1, 9)
                    if colours is not None:
                        rec["rgb"] = colours
                    rec.tofile(f)
                    total += len(corners)
                    self.report("read", total, 2 * max(total, self.src.estimate), message="staging")
        if total == 0:
            raise MeshError(f"{self.src.name}: the input has no triangles")
        if total >= 2**32 - 1:
            raise ValueError(f"{self.src.name}: {total} triangles; the format's ids hold at most 2^32 - 2")
        centre = 0.5 * (lo + hi)
        first_pass = 0 if known is not None else total  # progress: the bounds pass, if any

        root = scratch / "root.tri"
        count = 0
        degenerate = 0
        box_lo = np.full(3, np.inf, dtype=np.float32)
        box_hi = np.full(3, -np.inf, dtype=np.float32)
        done = 0

        def source_chunks() -> Iterator[tuple[np.ndarray, np.ndarray | None]]:
            """(corners in double, colours) per chunk, in input order."""
            if self.src.rereadable:
                yield from self.src.chunks()
            else:
                for staged_rec in _read_records(staged, self.staged_dtype, self.opt.chunk()):
                    colours = staged_rec["rgb"] if self.src.has_colours else None
                    yield staged_rec["c"].reshape(-1, 3, 3), colours

        with open(root, "wb") as f:
            for corners, colours in source_chunks():
                # Native: float32(vertex - centre) computed in double, as in the in-core
                # Scene (bit-identical vertices on both paths); zero-area triangles (in
                # those float32 coordinates) are left out and counted. A triangle's id is
                # its position in the input (`done` triangles precede this chunk).
                records, dropped, lo_k, hi_k = native.make_records(corners, colours, done, centre.tolist())
                degenerate += dropped
                if len(records):
                    box_lo = np.minimum(box_lo, np.asarray(lo_k, dtype=np.float32))
                    box_hi = np.maximum(box_hi, np.asarray(hi_k, dtype=np.float32))
                records.tofile(f)
                count += len(records)
                done += len(corners)
                self.report("read", first_pass + done, first_pass + total, message="writing records")
        staged.unlink(missing_ok=True)
        if count == 0:
            raise MeshError(f"{self.src.name}: all {total} triangles are degenerate (zero area)")
        return root, count, total, degenerate, centre, box_lo, box_hi

    # -- phase 2: split ---------------------------------------------------------------------

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
        split = _choose_splits(lo, hi, tight_lo, tight_hi, level)
        kids = self.sift(path, split)
        path.unlink()
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
        return split

    def sift(self, path: Path, split: _Split) -> list[Any]:
        files = [open(self.scratch / f"n{id(split)}-{s}.tri", "wb") for s in range(8)]
        counts = [0] * 8
        tlo = [np.full(3, np.inf, dtype=np.float32) for _ in range(8)]
        thi = [np.full(3, -np.inf, dtype=np.float32) for _ in range(8)]
        try:
            for rec in _read_records(path, self.dtype, self.opt.chunk()):
                # One native pass per chunk: a triangle goes to each cell whose closed
                # half-spaces its bounding box touches.
                parts, bounds = native.sift8(
                    rec.view(np.uint8).reshape(len(rec), self.dtype.itemsize), split.axes, split.splits,
                    split.slot_lo, split.slot_hi,
                )  # fmt: skip
                for s, part in enumerate(parts):
                    if len(part):
                        part.tofile(files[s])
                        counts[s] += len(part)
                        tlo[s] = np.minimum(tlo[s], bounds[s, :3])
                        thi[s] = np.maximum(thi[s], bounds[s, 3:])
                self.sifted += len(rec)
                self.report("split", self.sifted, self.sift_estimate, message=f"level {split.level}")
        finally:
            for f in files:
                f.close()
        out: list[Any] = []
        for s in range(8):
            fpath = Path(files[s].name)
            if counts[s] == 0:
                fpath.unlink()
                out.append(None)
            else:
                out.append((fpath, counts[s], split.slot_lo[s], split.slot_hi[s], tlo[s], thi[s]))
        return out

    # -- phase 3: build ---------------------------------------------------------------------

    def emit(self, node: _Part | _Split, writer: native.ModelWriter) -> int:
        if isinstance(node, _Split):
            handles = [self.emit(k, writer) if k is not None else -1 for k in node.children]
            return writer.add_inner_treelet(
                node.level, node.lo.tolist(), node.hi.tolist(), node.axes, node.splits, handles
            )
        recs = np.fromfile(node.path, dtype=self.dtype)
        node.path.unlink()
        self.part_base = self.built
        self.part_refs0 = self.refs_seen
        self.part_count = node.count
        handle = writer.add_subtree(
            recs["c"], recs["id"], recs["rgb"] if self.src.has_colours else None,
            node.lo.tolist(), node.hi.tolist(), node.level,
        )  # fmt: skip
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

    def run(self, scratch: Path, partial: Path) -> dict[str, Any]:
        self.scratch = scratch
        t = time.perf_counter()
        root, count, total, degenerate, centre, lo, hi = self.read(scratch)
        t = self.timed("read", t)

        limit = self.opt.incore_limit()
        self.sifted = 0
        # Each out-of-core level passes over every triangle once (plus duplicates).
        levels_needed = 0
        n = count
        while n > limit:
            n //= 8
            levels_needed += 1
        self.sift_estimate = max(1, count * levels_needed)
        tree = self.plan(root, count, lo, hi, lo, hi, 0, limit)
        t = self.timed("split", t)

        parts = list(_parts(tree))
        self.build_total = sum(p.count for p in parts)
        self.built = 0
        self.refs_seen = 0
        self.part_base = self.part_refs0 = self.part_count = 0
        self.dup = 1.5
        blocks_dir = scratch / "blocks"
        blocks_dir.mkdir()
        writer = native.ModelWriter(
            has_colours=self.src.has_colours,
            scratch_dir=str(blocks_dir),
            progress=self.on_refs,
            leaf_size=self.opt.leaf_size,
            traversal_cost=self.opt.traversal_cost,
            intersection_cost=self.opt.intersection_cost,
            empty_space_ratio=self.opt.empty_space_ratio,
            voxel_rays=self.opt.voxel_rays,
            threads=self.opt.threads,
        )
        self.report("build", 0, self.build_total)
        root_handle = self.emit(tree, writer)
        writer.finish(root_handle)
        stats = writer.stats
        level_files = writer.levels  # {level: (path, (n, 4) stored size, raw size, crc32, codec)}
        t = self.timed("build", t)

        node_levels = len(stats["level_blocks"])
        order = [*range(node_levels), -1]
        levels: list[tuple[int, int, int, int]] = []
        entries: list[tuple[int, int, int, int]] = []
        for level in order:
            es = [tuple(int(x) for x in e) for e in level_files[level][1]] if level in level_files else []
            if level >= 0:
                contents = (stats["level_nodes"][level], stats["level_voxels"][level])
            else:
                contents = (stats["stored_triangles"], stats["stored_vertices"])
            levels.append((len(entries), len(es), *contents))
            entries.extend(es)
        stored_total = sum(e[0] for e in entries)
        fields = {
            "flags": modelfile.FLAG_TRIANGLE_IDS | (modelfile.FLAG_COLOURS if self.src.has_colours else 0),
            "centre": tuple(float(x) for x in centre),
            "cell_lo": tuple(float(x) for x in lo),
            "cell_hi": tuple(float(x) for x in hi),
            "triangle_count": count,
            "input_triangles": total,
            "degenerate": degenerate + stats["degenerate"],
            "basic_nodes": stats["basic_nodes"],
            "lod_nodes": stats["lod_nodes"],
            "leaves": stats["leaves"],
            "voxels_one": stats["voxels_one"],
            "voxels_six": stats["voxels_six"],
            "references": stats["references"],
        }
        written = 0

        def blocks() -> Iterator[bytes]:
            nonlocal written
            for level in order:
                if level not in level_files:
                    continue
                path = Path(level_files[level][0])
                with open(path, "rb") as f:
                    while chunk := f.read(8 << 20):
                        written += len(chunk)
                        self.report("write", written, stored_total, unit="bytes")
                        yield chunk
                path.unlink()

        with open(partial, "wb") as out:
            size = modelfile.write_model_file(out, fields, levels, entries, blocks())
            out.flush()
            os.fsync(out.fileno())
        t = self.timed("write", t)

        raw_total = sum(e[1] for e in entries)
        return {
            "input": self.src.name,
            "output": str(self.output),
            "triangles": count,
            "input_triangles": total,
            "degenerate": degenerate,
            "file_bytes": size,
            "raw_bytes": raw_total,
            "compression_ratio": raw_total / stored_total if stored_total else 1.0,
            "bytes_per_triangle": size / count,
            "node_levels": node_levels,
            "blocks": len(entries),
            "parts": len(parts),
            "out_of_core_levels": _depth(tree),
            "incore_limit": limit,
            "seconds": time.perf_counter() - self.start,
            "phase_seconds": dict(self.phase_seconds),
            "triangles_per_second": count / max(1e-9, time.perf_counter() - self.start),
            "peak_rss_bytes": peak_rss_bytes(),
            "warnings": self.warnings,
            **{k: stats[k] for k in ("basic_nodes", "lod_nodes", "leaves", "voxels_one", "voxels_six",
                                     "references", "stored_triangles", "stored_vertices", "kd_build_ms",
                                     "emit_ms", "max_depth")},
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


def _read_records(path: Path, dtype: np.dtype, chunk: int) -> Iterator[np.ndarray]:
    """Sequential chunks of a scratch file. Plain reads, not a memory map: pages already
    processed must not stay in the resident set, which the budget is measured on."""
    with open(path, "rb") as f:
        while len(rec := np.fromfile(f, dtype=dtype, count=chunk)):
            yield rec


def _choose_splits(
    lo: np.ndarray, hi: np.ndarray, tight_lo: np.ndarray, tight_hi: np.ndarray, level: int
) -> _Split:
    """Median splits for three levels, in heap order: each halves the longest side of
    the occupied part of its cell, so empty space is cut away as it goes."""
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
        if not (ext[axis] > 0 and clo[axis] < value < chi[axis]):
            axis = int(np.argmax(chi - clo))
            value = np.float32(0.5 * (float(clo[axis]) + float(chi[axis])))
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
    return _Split(lo.astype(np.float32), hi.astype(np.float32), level, axes, splits, slot_lo, slot_hi)


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
    model file `output`; returns a report of counts, sizes and timings."""
    opt = options or BuildOptions()
    out = Path(output)
    if out.exists() and not opt.overwrite:
        raise FileExistsError(f"{out} exists; pass overwrite (--force) to replace it")
    if not out.parent.is_dir():
        raise FileNotFoundError(f"{out.parent}: no such directory for the output")
    if opt.memory < MIN_INCORE_TRIANGLES * INCORE_BYTES_PER_TRIANGLE:
        need = (MIN_INCORE_TRIANGLES * INCORE_BYTES_PER_TRIANGLE + (1 << 20) - 1) >> 20
        raise ValueError(f"memory budget too small: the builder needs at least {need} MiB")
    src = _open_input(source, opt.chunk())
    scratch = Path(tempfile.mkdtemp(prefix=".vastray-build-", dir=opt.scratch_dir or out.parent))
    partial = out.with_name(f".{out.name}.partial-{os.getpid()}")
    builder = _Builder(src, out, opt, progress, cancel)
    try:
        report = builder.run(scratch, partial)
        if cancel is not None and cancel.is_set():  # the last chance: nothing is in place yet
            raise BuildCancelledError("build cancelled")
        if out.exists() and not opt.overwrite:
            raise FileExistsError(f"{out} appeared during the build; not replacing it")
        os.replace(partial, out)
        return report
    finally:
        partial.unlink(missing_ok=True)
        shutil.rmtree(scratch, ignore_errors=True)
