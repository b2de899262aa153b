"""`vastray build`: the out-of-core model builder and its file, end to end.

Built models are read back through an independent pure-Python walker
(tests/modelwalk.py, written from format.h alone) and checked against the input:

* round trip, for a real mesh (bunny), a generated coloured scene, a raw float32 soup
  with degenerate and long sliver triangles, a triangle fan whose centre leaf is bigger
  than a triangle block, and a forced out-of-core build (the smallest memory budget, so
  the top of the tree is split on disk into several in-core parts): every
  non-degenerate triangle is in exactly the leaves whose cells it overlaps (a float64
  separating-axis test with a tolerance of 1e-5 of the model diagonal: a triangle
  overlapping a leaf's cell shrunk by it must be listed there, a listed one must
  overlap the cell grown by it), vertices are float32(vertex - centre) bit for bit,
  colours survive, LOD nodes sit exactly at treelet depth 2 with their radius half the
  cell diagonal and 1 or 6 well-formed voxel samples, the header and level table count
  what the walk finds;
* a full-detail render of the built model hits the same triangles as the in-core
  renderer, and its batch queries agree with the brute-force reference;
* damaged files (a flipped bit in a block, the header or the index, truncation, another
  version, not a model) give a ModelError that says what is wrong, and the CLI exits 2;
* the builder stays within its memory budget plus the stated fixed overhead (a child
  process building a soup three times the budget, its peak RSS read from VmHWM);
* failures, cancellation, Ctrl-C and SIGTERM leave nothing behind; an existing output
  is kept unless overwriting is asked for;
* progress phases come in order with monotone counts; the CLI builds, inspects and
  renders built models.
"""

from __future__ import annotations

import errno
import functools
import json
import os
import re
import shutil
import signal
import struct
import subprocess
import sys
import tempfile
import threading
import time
import zlib
from collections.abc import Callable
from dataclasses import dataclass
from functools import cached_property
from itertools import groupby
from pathlib import Path
from typing import TYPE_CHECKING, Any

import lz4.block
import numpy as np
import pytest
from modelwalk import Node, TriangleBlock, Walker, decode_sample
from PIL import Image

import vastray.render as vrender
from vastray import model_assembly, native, scenes
from vastray.build import (
    INCORE_BYTES_PER_TRIANGLE,
    MIN_INCORE_TRIANGLES,
    STATED_OVERHEAD_BYTES,
    BuildCancelledError,
    BuildOptions,
    BuildProgress,
    build_model,
)
from vastray.camera import frame_bounds
from vastray.mesh import MeshError
from vastray.modelfile import _HEADER_FIELDS, FLAG_COLOURS, HEADER_SIZE, VERSION, ModelError, ModelFile
from vastray.outofcore import OutOfCoreModel, make_cache
from vastray.render import SceneRenderer
from vastray.triangle_readers import open_triangles
from vastray.units import parse_bytes

if TYPE_CHECKING:
    from conftest import Agreement, ModelMesh

VASTRAY = Path(sys.executable).parent / "vastray"  # the console script
# The smallest budget the builder accepts, rounded up to whole MiB (5 MiB): parts of at
# most ~21,800 triangles, so a 100k-triangle input is split out of core.
SMALL_MEMORY = ((MIN_INCORE_TRIANGLES * INCORE_BYTES_PER_TRIANGLE >> 20) + 1) << 20
REL_TOL = 1e-5  # overlap tolerance, relative to the model's diagonal
UNITS = np.eye(3)


# ---- geometry -----------------------------------------------------------------------------------


def overlaps(tri: np.ndarray, lo: np.ndarray, hi: np.ndarray, grow: float) -> np.ndarray:
    """Triangle/box overlap in float64 by the separating axis theorem (the box's three
    axes, the triangle's normal, the nine edge x axis cross products), with the box
    grown by `grow` on every side (shrunk when negative; an inverted box overlaps
    nothing). tri (n, 3, 3); lo, hi (n, 3) or (3,). Returns (n,) bool."""
    lo = np.asarray(lo, dtype=np.float64)
    hi = np.asarray(hi, dtype=np.float64)
    c = 0.5 * (lo + hi)
    h = 0.5 * (hi - lo) + grow
    v = tri - c[..., None, :]
    ok = (h >= 0).all(-1) & (v.min(-2) <= h).all(-1) & (v.max(-2) >= -h).all(-1)
    e = [v[..., 1, :] - v[..., 0, :], v[..., 2, :] - v[..., 1, :], v[..., 0, :] - v[..., 2, :]]
    for axis in [np.cross(e[0], e[1])] + [np.cross(edge, u) for edge in e for u in UNITS]:
        p = np.einsum("...kj,...j->...k", v, axis)
        r = (np.abs(axis) * h).sum(-1)
        ok &= (p.min(-1) <= r) & (p.max(-1) >= -r)
    return ok


def pairs_overlap(
    tri: np.ndarray, ids: np.ndarray, lo: np.ndarray, hi: np.ndarray, grow: float
) -> np.ndarray:
    """overlaps(tri[ids], lo, hi, grow) for many (triangle, cell) pairs, in chunks."""
    step = 1 << 16
    return np.concatenate(
        [
            overlaps(tri[ids[k : k + step]], lo[k : k + step], hi[k : k + step], grow)
            for k in range(0, len(ids), step)
        ]
        or [np.zeros(0, dtype=bool)]
    )


def pack_rgb(colours: np.ndarray) -> np.ndarray:
    c = colours.astype(np.uint32)
    return c[:, 0] | (c[:, 1] << 8) | (c[:, 2] << 16)


# ---- built models --------------------------------------------------------------------------------


@dataclass
class Case:
    name: str
    source: Path | str  # what build_model was given
    corners: np.ndarray  # (n, 3, 3) float64 input triangles, in input order (= triangle ids)
    colours: np.ndarray | None  # (n, 3) uint8
    path: Path
    report: dict[str, Any]
    events: list[BuildProgress]
    incore_source: str | None  # for vrender.load_model; None: a native.Scene from the corners

    @cached_property
    def model(self) -> ModelFile:
        return ModelFile(self.path)

    @cached_property
    def walker(self) -> Walker:
        return Walker(self.model)

    @cached_property
    def nodes(self) -> list[Node]:
        return list(self.walker.walk())

    @cached_property
    def leaves(self) -> list[Node]:
        return [n for n in self.nodes if n.kind == "leaf"]

    @cached_property
    def local(self) -> np.ndarray:
        """The input as the format stores it: float32, relative to the header's centre."""
        return (self.corners - np.array(self.model.header["centre"])).astype(np.float32)

    @cached_property
    def triangles(self) -> np.ndarray:
        """The stored triangles in float64 (what the overlap tests work on)."""
        return self.local.astype(np.float64)

    @cached_property
    def valid(self) -> np.ndarray:
        """Not degenerate: non-zero area in the stored float32 coordinates."""
        t = self.triangles
        return (np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]) != 0).any(axis=1)

    @cached_property
    def tolerance(self) -> float:
        h = self.model.header
        return REL_TOL * float(np.linalg.norm(np.subtract(h["cell_hi"], h["cell_lo"])))

    @cached_property
    def pairs(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Every (triangle id, leaf lo, leaf hi) reference, one row each."""
        ids = np.concatenate([leaf.ids for leaf in self.leaves]).astype(np.int64)
        counts = [len(leaf.ids) for leaf in self.leaves]
        lo = np.repeat(np.array([leaf.lo for leaf in self.leaves], dtype=np.float64), counts, axis=0)
        hi = np.repeat(np.array([leaf.hi for leaf in self.leaves], dtype=np.float64), counts, axis=0)
        return ids, lo, hi


def write_soup(path: Path, rng: np.random.Generator) -> np.ndarray:
    """A raw float32 soup: small random triangles in a unit cube, long slivers across it
    (they straddle many cells) and a few degenerate ones (repeated, collinear, a point)."""
    small = rng.random((12_000, 1, 3)) + rng.normal(scale=0.01, size=(12_000, 3, 3))
    a, b = rng.random((400, 3)), rng.random((400, 3))
    slivers = np.stack([a, b, a + rng.normal(scale=0.003, size=(400, 3))], axis=1)
    tris = np.concatenate([small, slivers]).astype(np.float32)
    rng.shuffle(tris)
    tris[7] = [tris[7, 0], tris[7, 0], tris[7, 2]]  # repeated corner
    tris[5000] = [[0.25, 0.5, 0.5], [0.5, 0.5, 0.5], [0.75, 0.5, 0.5]]  # collinear (also once centred)
    tris[-1] = [tris[-1, 1]] * 3  # a point
    tris.astype("<f4").tofile(path)
    return tris.astype(np.float64)


def write_fan(path: Path, n: int = 3_000) -> np.ndarray:
    """A disc that is a fan of n triangles around one centre vertex (a tessellated
    cylinder cap or cone tip), off the origin so no split plane passes through the centre:
    no kd-tree cell around the centre gets fewer than all n, and 3,000 triangles with
    their vertices do not fit in one 64 KiB triangle block."""
    a = np.linspace(0.0, 2.0 * np.pi, n + 1)
    fan = np.zeros((n, 3, 3))
    fan[:, :, 0], fan[:, :, 1] = 0.3, 0.1
    fan[:, 1, 0] += np.cos(a[:-1])
    fan[:, 1, 1] += np.sin(a[:-1])
    fan[:, 2, 0] += np.cos(a[1:])
    fan[:, 2, 1] += np.sin(a[1:])
    tris = fan.astype(np.float32)
    tris.astype("<f4").tofile(path)
    return tris.astype(np.float64)


def write_grid_soup(path: Path, n: int) -> int:
    """A finely tessellated wavy height field over [0, 1]^2 (n x n quads, 2 triangles
    each) streamed to a raw float32 soup row by row. Returns the triangle count."""
    xs = np.linspace(0.0, 1.0, n + 1)

    def point(x: np.ndarray, y: float) -> np.ndarray:
        return np.stack([x, np.full_like(x, y), 0.05 * np.sin(12 * x) * np.cos(9 * y)], axis=-1)

    with open(path, "wb") as f:
        for j in range(n):
            p00, p10 = point(xs[:-1], xs[j]), point(xs[1:], xs[j])
            p01, p11 = point(xs[:-1], xs[j + 1]), point(xs[1:], xs[j + 1])
            rows = np.stack([np.stack([p00, p10, p11], 1), np.stack([p00, p11, p01], 1)], 1)
            rows.reshape(-1, 3, 3).astype("<f4").tofile(f)
    return 2 * n * n


def concat_generated(name: str, triangles: int, seed: int) -> tuple[np.ndarray, np.ndarray | None]:
    chunks = list(scenes.generate(name, triangles, seed))
    corners = np.concatenate([v[f] for v, f, _ in chunks])
    colours = None if chunks[0][2] is None else np.concatenate([c for _, _, c in chunks])
    return corners, colours


def read_stream(path: Path) -> tuple[np.ndarray, np.ndarray | None]:
    chunks = list(open_triangles(path).chunks())
    colours = None if chunks[0].colours is None else np.concatenate([c.colours for c in chunks])
    return np.concatenate([c.corners for c in chunks]), colours


CASES = ("bunny", "plant", "soup", "fan", "out-of-core")


@pytest.fixture(scope="module")
def workdir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tmp_path_factory.mktemp("build")


@pytest.fixture(scope="module")
def ooc_ply(workdir: Path) -> Path:
    """A 100k-triangle coloured plant as binary PLY (streamed, re-readable input)."""
    path = workdir / "inputs" / "plant100k.ply"
    path.parent.mkdir(exist_ok=True)
    scenes.write_scene("plant", 100_000, 2, path)
    return path


@pytest.fixture(scope="module")
def built(
    workdir: Path, ooc_ply: Path, models_folder: Path, load_model: Callable[[Path], ModelMesh]
) -> Callable[[str], Case]:
    """Builds each case once per module, on first use."""
    inputs = workdir / "inputs"

    @functools.cache
    def get(name: str) -> Case:
        options = BuildOptions()
        incore: str | None
        source: Path | str
        if name == "bunny":
            source = models_folder / "stanford-bunny.obj"
            mesh = load_model(source)
            corners, colours, incore = mesh.vertices[mesh.faces.astype(np.int64)], None, str(source)
        elif name == "plant":
            source = "scene:plant:30000:1"
            (corners, colours), incore = concat_generated("plant", 30_000, 1), source
        elif name == "soup":
            source = inputs / "soup.f32"
            corners, colours, incore = write_soup(source, np.random.default_rng(5)), None, None
        elif name == "fan":
            source = inputs / "fan.f32"
            corners, colours, incore = write_fan(source), None, None
        else:
            source = ooc_ply
            (corners, colours), incore = read_stream(ooc_ply), str(ooc_ply)
            options = BuildOptions(memory=SMALL_MEMORY)
        events: list[BuildProgress] = []
        path = workdir / f"{name}.vast"
        report = build_model(source, path, options, progress=events.append)
        return Case(name, source, corners, colours, path, report, events, incore)

    return get


@pytest.fixture(params=CASES)
def case(request: pytest.FixtureRequest, built: Callable[[str], Case]) -> Case:
    return built(request.param)


# ---- round trip ----------------------------------------------------------------------------------


def test_header_report_and_walk_agree(case: Case) -> None:
    h, r = case.model.header, case.report
    n_valid = int(case.valid.sum())
    assert h["input_triangles"] == r["input_triangles"] == len(case.corners)
    assert h["triangle_count"] == r["triangles"] == n_valid
    assert h["degenerate"] == len(case.corners) - n_valid
    if case.name == "soup":
        assert h["degenerate"] == 3
    kinds = {k: sum(1 for n in case.nodes if n.kind == k) for k in ("basic", "lod", "leaf")}
    assert (kinds["basic"], kinds["lod"], kinds["leaf"]) == (h["basic_nodes"], h["lod_nodes"], h["leaves"])
    assert sum(len(leaf.ids) for leaf in case.leaves) == h["references"] == r["references"]
    ones = sum(1 for n in case.nodes if n.kind == "lod" and len(n.samples) == 1)
    assert (ones, kinds["lod"] - ones) == (h["voxels_one"], h["voxels_six"])
    packed = sum(1 for n in case.nodes if n.kind == "lod" and len(n.voxel_words) == 4)
    assert packed == h["voxels_packed"] == r["voxels_packed"] <= h["voxels_six"]
    # The walk reaches every block of every level, and nothing else is in the file.
    assert sorted(case.walker.raw) == list(range(len(case.model.blocks)))
    # The level table's contents: nodes and voxels per node level, then triangle records
    # and vertices over all triangle blocks.
    per_level = [
        (
            sum(1 for n in case.nodes if n.level == level),
            sum(1 for n in case.nodes if n.level == level and n.kind == "lod"),
        )
        for level in range(case.model.node_levels)
    ]
    blocks = case.walker.tri_blocks.values()
    per_level.append((sum(len(b.ids) for b in blocks), sum(len(b.vertices) for b in blocks)))
    assert case.model.level_contents == per_level
    assert per_level[-1] == (r["stored_triangles"], r["stored_vertices"])
    assert case.model.node_levels == r["node_levels"] >= 2
    if case.name == "out-of-core":
        assert r["incore_parts"] > 1 and r["out_of_core_levels"] >= 1, r
    else:
        assert r["incore_parts"] == 1 and r["out_of_core_levels"] == 0, r


def test_vertices_and_colours_round_trip(case: Case) -> None:
    ids, _, _ = case.pairs
    vertices = np.concatenate([leaf.vertices for leaf in case.leaves])
    # Bit for bit: float32 of (input vertex - centre), the subtraction in double.
    mismatch = np.flatnonzero((vertices != case.local[ids]).any(axis=(1, 2)))
    assert len(mismatch) == 0, f"{len(mismatch)} references with other vertices, e.g. ids {ids[mismatch[:5]]}"
    flags = case.model.header["flags"]
    if case.colours is None:
        assert not flags & FLAG_COLOURS and not case.model.has_colours
        # The walker parses triangle blocks without a colour section: a block size that
        # matches its section counts means there is none.
        assert all(leaf.colours is None for leaf in case.leaves)
    else:
        assert flags & FLAG_COLOURS and case.model.has_colours
        stored = np.concatenate([leaf.colours for leaf in case.leaves])
        np.testing.assert_array_equal(stored, pack_rgb(case.colours)[ids])
        assert len(np.unique(stored)) > 1


def test_a_leaf_bigger_than_a_triangle_block(built: Callable[[str], Case]) -> None:
    """The fan's centre leaf holds all 3,000 triangles: more than one 64 KiB triangle
    block takes, so its list continues into the following blocks (checked for every
    case by the round-trip tests above and below)."""
    case = built("fan")
    biggest = max(len(leaf.ids) for leaf in case.leaves)
    assert biggest == len(case.corners) == 3_000
    assert sorted(next(leaf for leaf in case.leaves if len(leaf.ids) == biggest).ids) == list(range(3_000))


def children_of(nodes: list[Node]) -> list[list[int | None]]:
    """[left, right] child indices of every node of a pre-order walk (None: no child)."""
    kids: list[list[int | None]] = [[None, None] for _ in nodes]
    open_sides: list[tuple[int, list[int]]] = []  # inner nodes whose children are still coming
    for i, node in enumerate(nodes):
        if open_sides:
            parent, sides = open_sides[-1]
            kids[parent][sides.pop(0)] = i
            if not sides:
                open_sides.pop()
        if node.kind != "leaf":
            open_sides.append((i, [side for side in (0, 1) if not node.empty[side]]))
    assert not open_sides, "the walk ended inside a subtree"
    return kids


# Not on the fan: its 540k references around one vertex make the candidate sets huge.
@pytest.mark.parametrize("name", [name for name in CASES if name != "fan"])
def test_every_triangle_is_in_every_leaf_it_overlaps(built: Callable[[str], Case], name: str) -> None:
    """Each triangle that overlaps a leaf's cell shrunk by the tolerance is listed in that
    leaf, and none overlaps an empty child's cell (a cell with no subtree)."""
    case = built(name)
    ids, _, _ = case.pairs
    reached = np.zeros(len(case.corners), dtype=bool)
    reached[ids] = True
    assert reached[case.valid].all(), f"unreachable triangles: {np.flatnonzero(case.valid & ~reached)[:10]}"
    assert not reached[~case.valid].any(), "a degenerate triangle was stored"

    # Descend with the triangles whose bounding box meets each cell (a superset of those
    # that overlap it; only the split axis changes from parent to child), collecting
    # (cell, candidates) at every leaf and every empty child; test them all at the end.
    tri, n = case.triangles, len(case.corners)
    tlo, thi = tri.min(axis=1), tri.max(axis=1)
    cells: list[tuple[int, np.ndarray, np.ndarray, np.ndarray]] = []  # (leaf node index or -1, lo, hi, ids)
    nodes, kids = case.nodes, children_of(case.nodes)
    stack = [(0, np.flatnonzero(case.valid))]
    while stack:
        i, cand = stack.pop()
        node = nodes[i]
        if node.kind == "leaf":
            cells.append((i, node.lo, node.hi, cand))
            continue
        split = np.float32(node.split)
        left = cand[tlo[cand, node.axis] <= split]
        right = cand[thi[cand, node.axis] >= split]
        for side, sub in ((0, left), (1, right)):
            child = kids[i][side]
            if child is None:
                cells.append((-1, *node.child_cell(side), sub))
            else:
                stack.append((child, sub))
    owner = np.concatenate([np.full(len(c[3]), c[0]) for c in cells])
    cand_ids = np.concatenate([c[3] for c in cells])
    lo = np.concatenate([np.broadcast_to(c[1], (len(c[3]), 3)) for c in cells]).astype(np.float64)
    hi = np.concatenate([np.broadcast_to(c[2], (len(c[3]), 3)) for c in cells]).astype(np.float64)
    clear = pairs_overlap(tri, cand_ids, lo, hi, -case.tolerance)
    in_empty = clear & (owner < 0)
    assert not in_empty.any(), f"triangles {np.unique(cand_ids[in_empty])[:10]} overlap an empty cell"
    listed = np.concatenate([i * n + x.ids.astype(np.int64) for i, x in enumerate(nodes) if x.kind == "leaf"])
    key = owner * n + cand_ids
    lost = clear & (owner >= 0) & ~np.isin(key, listed)
    detail = [f"id {cand_ids[j]} not in leaf {lo[j]}..{hi[j]}" for j in np.flatnonzero(lost)[:3]]
    assert not lost.any(), f"{lost.sum()} triangles missing from leaves they overlap: {detail}"


def test_leaves_hold_only_triangles_that_overlap_them(case: Case) -> None:
    ids, lo, hi = case.pairs
    ok = pairs_overlap(case.triangles, ids, lo, hi, case.tolerance)
    bad = np.flatnonzero(~ok)
    detail = [f"id {ids[i]} in leaf {lo[i].tolist()}..{hi[i].tolist()}" for i in bad[:3]]
    assert len(bad) == 0, (
        f"{len(bad)} of {len(ids)} leaf references are triangles that miss the leaf's cell "
        f"(grown by {case.tolerance:.3g}): {detail}"
    )


def test_out_of_core_cells_hold_only_triangles_that_overlap_them(built: Callable[[str], Case]) -> None:
    """The cells the builder splits on disk (the treelet roots of LOD level 1, each an
    in-core part or a further split) get only triangles that overlap them; the split
    sifts by bounding box, so the part builder must drop the ones that only come near."""
    case = built("out-of-core")
    tri, tol = case.triangles, case.tolerance
    roots = [i for i, n in enumerate(case.nodes) if n.level == 1 and n.depth == 0]
    assert len(roots) > 1
    bad: list[str] = []
    for k, start in enumerate(roots):
        end = roots[k + 1] if k + 1 < len(roots) else len(case.nodes)
        root = case.nodes[start]
        below = [n for n in case.nodes[start:end] if n.kind == "leaf" and n.level >= 1]
        ids = np.unique(np.concatenate([n.ids for n in below]).astype(np.int64))
        outside = ids[~overlaps(tri[ids], root.lo, root.hi, tol)]
        if len(outside):
            bad.append(f"{len(outside)} of {len(ids)} in cell {root.lo}..{root.hi}, e.g. {outside[:3]}")
    assert not bad, "triangles that miss an out-of-core cell were built into it: " + "; ".join(bad)


def test_lod_nodes_and_voxels(case: Case) -> None:
    lods = [n for n in case.nodes if n.kind == "lod"]
    assert lods
    for n in case.nodes:
        assert 0 <= n.depth <= 2
        if n.kind != "leaf":
            # LOD nodes exactly at treelet depth 2 (global depth 3k + 2), every inner node there.
            assert (n.kind == "lod") == (n.depth == 2), (n.kind, n.level, n.depth)
    for n in lods:
        # The voxel's box is the node's cell: the radius is half its diagonal.
        half_diagonal = 0.5 * float(np.linalg.norm((n.hi - n.lo).astype(np.float64)))
        assert n.radius == pytest.approx(half_diagonal, rel=1e-6, abs=1e-30)
        assert len(n.samples) in (1, 6)
        flags = {s >> 31 for s in n.samples}
        assert flags == ({1} if len(n.samples) == 1 else {0})
    colours, normals = zip(*(decode_sample(s) for n in lods for s in n.samples), strict=True)
    colours_a, normals_a = np.array(colours), np.array(normals)
    assert np.isfinite(normals_a).all()
    np.testing.assert_allclose(np.linalg.norm(normals_a, axis=1), 1.0, rtol=1e-9)
    assert ((colours_a >= 0) & (colours_a <= 1)).all()
    if case.colours is None:
        # No colours in the input: every voxel is the default grey 0.75, quantised to 5 bits.
        np.testing.assert_array_equal(colours_a, np.full_like(colours_a, round(0.75 * 31) / 31))
    else:
        assert len({tuple(c) for c in colours_a}) > 10
    if case.name in ("bunny", "plant", "out-of-core"):
        # Both one- and six-sample voxels occur on a real model.
        assert {len(n.samples) for n in lods} == {1, 6}


@pytest.mark.slow
def test_generated_scene_of_several_chunks_keeps_exact_vertices(tmp_path: Path) -> None:
    """A generated scene arrives in chunks of up to 2^20 triangles and can be read only
    once; the builder stages it before it knows the centre. The stored vertices must
    still be float32(vertex - centre), as for files and as in the in-core Scene."""
    chunks = list(scenes.generate("spheres", 1_100_000, 1))
    assert len(chunks) > 1
    corners = np.concatenate([v[f.astype(np.int64)] for v, f, _ in chunks])
    del chunks
    build_model("scene:spheres:1100000:1", tmp_path / "m.vast")
    with ModelFile(tmp_path / "m.vast") as model:
        local = (corners - np.array(model.header["centre"])).astype(np.float32)
        first, count = model.levels[-1]
        differ = total = 0
        for b in range(first, first + count):
            tb = TriangleBlock.parse(model.read_block(b), model.has_colours)
            stored = tb.vertices[tb.triangles.astype(np.int64)]
            differ += int((stored != local[tb.ids]).any(axis=(1, 2)).sum())
            total += len(tb.ids)
    assert total >= len(corners)
    assert differ == 0, f"{differ} of {total} stored triangles differ from float32(vertex - centre)"


# ---- rendering the built model -------------------------------------------------------------------


def incore_scene(case: Case) -> native.Scene:
    if case.incore_source is not None:
        return vrender.load_model(case.incore_source).scene
    n = len(case.corners)
    return native.Scene(case.corners.reshape(-1, 3), np.arange(3 * n, dtype=np.uint32).reshape(n, 3))


@pytest.mark.parametrize("name", CASES)
def test_full_detail_render_matches_in_core(built: Callable[[str], Case], name: str) -> None:
    case = built(name)
    decoded = vrender.load_model(str(case.path))
    assert decoded.build_seconds == 0.0  # decoded, not rebuilt from a mesh
    incore = incore_scene(case)
    lo, hi = incore.bounds
    np.testing.assert_allclose(decoded.scene.bounds, incore.bounds, rtol=0, atol=1e-6 * np.ptp([lo, hi]))
    for direction in ((1.0, 0.7, 1.3), (-0.6, -0.5, -1.0)):
        camera = frame_bounds(lo, hi, width=160, height=120, direction=direction)
        ours, ref = decoded.render(camera), SceneRenderer(incore, "in core").render(camera)
        assert ((ours.prim >= 0) == (ref.prim >= 0)).all(), "hit/miss differs"
        assert (ref.prim >= 0).mean() > 0.1
        differ = ours.prim != ref.prim
        rel = np.abs(ours.depth[differ] - ref.depth[differ]) / ref.depth[differ]
        assert (rel <= 1e-5).all(), f"{differ.sum()} pixels hit other triangles, not near-ties"
        both = ours.prim >= 0
        np.testing.assert_allclose(ours.depth[both], ref.depth[both], rtol=1e-5)


@pytest.mark.parametrize("name", ["bunny", "out-of-core"])
def test_batch_intersect_matches_reference(
    built: Callable[[str], Case], name: str, reference_check: Callable[..., Agreement]
) -> None:
    case = built(name)
    with ModelFile(case.path) as model:
        scene = model.to_scene()
    assert scene.triangle_count == len(case.corners)
    n = len(case.corners)
    vertices, faces = case.corners.reshape(-1, 3), np.arange(3 * n, dtype=np.uint32).reshape(n, 3)
    lo, hi = vertices.min(axis=0), vertices.max(axis=0)
    origins, directions = frame_bounds(lo, hi, width=64, height=48).primary_rays()
    a = reference_check(scene, vertices, faces, origins, directions, length=float(np.linalg.norm(hi - lo)))
    assert a.hits > 0.1 * a.rays
    assert a.nonfinite == 0, a.summary()
    assert len(a.bad_mismatches) == 0 and a.graze_mismatches <= 2, a.summary()
    assert len(a.bad_t) == 0 and len(a.bad_prims) == 0, a.summary()


# ---- damaged files -------------------------------------------------------------------------------


def header_offset(name: str) -> int:
    fmt = "<"
    for field_name, code in _HEADER_FIELDS:
        if field_name == name:
            return struct.calcsize(fmt)
        fmt += code
    raise KeyError(name)


def flip_bit(path: Path, offset: int, bit: int = 3) -> None:
    with open(path, "r+b") as f:
        f.seek(offset)
        byte = f.read(1)[0]
        f.seek(offset)
        f.write(bytes([byte ^ (1 << bit)]))


def run_cli(*args: str, cwd: Path, timeout: float = 120) -> subprocess.CompletedProcess[str]:
    return subprocess.run([str(VASTRAY), *args], cwd=cwd, capture_output=True, text=True, timeout=timeout)


@pytest.fixture
def damaged(built: Callable[[str], Case], tmp_path: Path) -> Path:
    """A fresh copy of the built bunny to damage."""
    copy = tmp_path / "bunny.vast"
    shutil.copyfile(built("bunny").path, copy)
    return copy


def test_flipped_bit_in_a_block_names_the_block(damaged: Path) -> None:
    with ModelFile(damaged) as model:
        levels = model.levels
        blocks = list(model.blocks)
    # The first block of every level, the triangle level included.
    for level, (first, count) in enumerate(levels):
        assert count > 0
        e = blocks[first]
        flip_bit(damaged, e.offset + e.stored_size // 2)
        with ModelFile(damaged) as model:  # header and index are intact: it opens
            # named as inspect numbers them
            name = "triangle level" if level == len(levels) - 1 else f"LOD level {level}"
            with pytest.raises(ModelError, match=rf"\bblock {first} \({name}\) checksum mismatch"):
                model.read_block(first)
            with pytest.raises(ModelError, match=rf"\bblock {first}\b"):
                model.verify()
            other = first + 1 if first + 1 < len(blocks) else 0
            if blocks[other].offset != e.offset:
                assert len(model.read_block(other)) == blocks[other].raw_size  # the rest still reads
        flip_bit(damaged, e.offset + e.stored_size // 2)  # repair
    with ModelFile(damaged) as model:
        model.verify()


def test_flipped_bit_anywhere_in_the_header_is_detected(damaged: Path) -> None:
    magic, version = header_offset("magic"), header_offset("version")
    assert (magic, version) == (0, 8)
    for offset in range(HEADER_SIZE):
        flip_bit(damaged, offset, bit=offset % 8)
        if offset < version:
            expected = "not a vastray model"
        elif offset < version + 4:
            flipped = VERSION ^ (1 << (8 * (offset - version) + offset % 8))
            # A flip to another version this vastray reads (3 -> 2) is caught by the CRC.
            expected = "header checksum mismatch" if 1 <= flipped <= VERSION else "format version"
        else:
            expected = "header checksum mismatch"
        with pytest.raises(ModelError, match=expected):
            ModelFile(damaged)
        flip_bit(damaged, offset, bit=offset % 8)
    ModelFile(damaged).close()


def test_flipped_bit_in_the_index_is_detected(damaged: Path) -> None:
    with ModelFile(damaged) as model:
        index_size = model.header["data_offset"] - HEADER_SIZE
    assert index_size > 0
    for offset in (HEADER_SIZE, HEADER_SIZE + index_size // 2, HEADER_SIZE + index_size - 1):
        flip_bit(damaged, offset)
        with pytest.raises(ModelError, match="index checksum mismatch"):
            ModelFile(damaged)
        flip_bit(damaged, offset)


def test_truncated_file(damaged: Path) -> None:
    size = damaged.stat().st_size
    with open(damaged, "r+b") as f:
        f.truncate(size - 1)
    with pytest.raises(ModelError, match=rf"file is {size - 1} bytes but its header says {size} \(truncated"):
        ModelFile(damaged)
    with open(damaged, "r+b") as f:
        f.truncate(100)
    with pytest.raises(ModelError, match="truncated: 100 bytes, shorter than the 256-byte header"):
        ModelFile(damaged)


def rewrite_version(path: Path, version: int) -> None:
    """Sets the version field and recomputes the header checksum, so only the version differs."""
    data = bytearray(path.read_bytes())
    struct.pack_into("<I", data, header_offset("version"), version)
    crc_at = header_offset("header_crc32")
    struct.pack_into("<I", data, crc_at, 0)
    struct.pack_into("<I", data, crc_at, zlib.crc32(bytes(data[:HEADER_SIZE])))
    path.write_bytes(bytes(data))


def test_other_format_version(damaged: Path) -> None:
    rewrite_version(damaged, VERSION)  # the checksum recomputation itself is right
    ModelFile(damaged).close()
    rewrite_version(damaged, VERSION + 1)
    expected = rf"format version {VERSION + 1} is not supported .*versions 1 to {VERSION}"
    with pytest.raises(ModelError, match=expected):
        ModelFile(damaged)


def test_not_a_model(tmp_path: Path, ooc_ply: Path) -> None:
    empty = tmp_path / "empty.vast"
    empty.write_bytes(b"")
    for path in (ooc_ply, empty):
        with pytest.raises(ModelError, match="not a vastray model"):
            ModelFile(path)
    result = run_cli("inspect", str(ooc_ply), cwd=tmp_path)
    assert result.returncode == 2
    assert "vastray: error:" in result.stderr and "not a vastray model" in result.stderr


def test_cli_on_a_damaged_block(damaged: Path, tmp_path: Path) -> None:
    with ModelFile(damaged) as model:
        block = model.levels[-1][0] + 1  # a triangle block
        e = model.blocks[block]
    flip_bit(damaged, e.offset + 5)
    result = run_cli("inspect", "--verify", str(damaged), cwd=tmp_path)
    assert result.returncode == 2, result.stdout
    assert re.search(rf"vastray: error: .*\bblock {block}\b.*checksum", result.stderr), result.stderr
    assert "Traceback" not in result.stderr
    png = tmp_path / "out.png"
    # Rendering treats a damaged block as missing: the image is drawn (voxels above it
    # stand in), the block is named, and the exit status says the image is not full
    # detail. A level-1 node block lies under most pixels of any framed view.
    with ModelFile(damaged) as model:
        assert len(model.levels) > 2
        block = model.levels[1][0]
        e = model.blocks[block]
    flip_bit(damaged, e.offset + 5)
    result = run_cli("render", str(damaged), "--size", "32x24", "-o", str(png), cwd=tmp_path)
    assert result.returncode == 3, result.stderr
    assert re.search(rf"vastray: warning: .*\bblock {block}\b.*checksum", result.stderr), result.stderr
    assert "Traceback" not in result.stderr
    assert png.exists()


# ---- memory budget -------------------------------------------------------------------------------

# Peak RSS of the child's own address space: VmHWM, reset at exec. (ru_maxrss is not
# usable here: Linux carries the parent's high-water mark over fork/vfork + exec, so a
# child of this test process would report this process's size.)
_MEMORY_CHILD = """
import json, resource, sys
from vastray.build import BuildOptions, build_model
threads = int(sys.argv[4]) if len(sys.argv) > 4 else 0  # 0: every core
report = build_model(sys.argv[1], sys.argv[2], BuildOptions(memory=int(sys.argv[3]), threads=threads))
with open("/proc/self/status") as f:
    hwm = next(int(line.split()[1]) * 1024 for line in f if line.startswith("VmHWM:"))
print(json.dumps({"peak": hwm, "ru_maxrss": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024,
                  "report": report}))
"""


def build_within_budget(source: Path, out: Path, budget: int, threads: int = 0) -> dict[str, Any]:
    """Builds `source` in a child process of its own and checks that its peak RSS stayed
    within `budget` plus the stated overhead; the build report."""
    child = subprocess.run(
        [sys.executable, "-c", _MEMORY_CHILD, str(source), str(out), str(budget), str(threads)],
        cwd=out.parent, capture_output=True, text=True, timeout=240,
    )  # fmt: skip
    assert child.returncode == 0, child.stderr
    result = json.loads(child.stdout)
    assert result["peak"] <= budget + STATED_OVERHEAD_BYTES, (
        f"peak RSS {result['peak'] / 2**20:.0f} MiB > budget {budget >> 20} MiB "
        f"+ {STATED_OVERHEAD_BYTES >> 20} MiB overhead"
    )
    return result["report"]


@pytest.mark.slow
@pytest.mark.timeout(300)
def test_build_stays_within_its_memory_budget(tmp_path: Path) -> None:
    budget = parse_bytes("32M")
    soup = tmp_path / "grid.f32"
    triangles = write_grid_soup(soup, 1200)  # 2.88M triangles, 99 MiB
    assert soup.stat().st_size >= 3 * budget
    out = tmp_path / "grid.vast"
    report = build_within_budget(soup, out, budget)
    assert report["triangles"] == triangles
    assert report["incore_parts"] > 1 and report["out_of_core_levels"] >= 1
    with ModelFile(out) as model:
        assert model.header["triangle_count"] == triangles
    assert sorted(os.listdir(tmp_path)) == ["grid.f32", "grid.vast"]


@pytest.mark.slow
@pytest.mark.timeout(300)
def test_a_build_on_many_threads_stays_within_its_memory_budget(tmp_path: Path) -> None:
    """The kd build's helper threads copy the references they take, so an in-core part
    needs more memory per triangle on more threads. Parts stay sized for 2 threads (the
    model must not depend on the thread count); the writer runs on fewer threads where
    the largest part leaves no room. Here 16 threads asked for (oversubscribed where
    there are fewer cores: the memory is the same) on one 3.4M-triangle part and a
    512 MiB budget, which all 16 passed by over 200 MiB (874 MiB against 640)."""
    budget = parse_bytes("512M")
    soup = tmp_path / "grid.f32"
    triangles = write_grid_soup(soup, 1300)  # 3.38M triangles: one part
    report = build_within_budget(soup, tmp_path / "grid.vast", budget, threads=16)
    assert report["triangles"] == triangles
    assert report["incore_parts"] == 1
    assert 2 <= report["writer_threads"] < 16


_BIG_PARENT = """
import json, subprocess, sys
big = bytes(range(256)) * (3 << 19)  # 384 MiB, every page touched
child = subprocess.run([sys.executable, "-c", sys.argv[1], *sys.argv[2:]], capture_output=True, text=True)
sys.stderr.write(child.stderr)
print(child.stdout, end="")
sys.exit(child.returncode)
"""


def test_reported_peak_rss_is_the_builders_own(tmp_path: Path) -> None:
    """The report's (and `vastray build`'s) peak RSS is the builder's, also when it is
    started by a bigger process (a server, a notebook): here a parent holding 384 MiB."""
    result = subprocess.run(
        [sys.executable, "-c", _BIG_PARENT, _MEMORY_CHILD, "scene:plant:30000:1", str(tmp_path / "m.vast"),
         str(32 << 20)],
        cwd=tmp_path, capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert result.returncode == 0, result.stderr
    out = json.loads(result.stdout)
    reported, own = out["report"]["peak_rss_bytes"], out["peak"]
    assert own < 256 << 20
    assert reported <= own + (8 << 20), (
        f"reported {reported >> 20} MiB, the process's own peak {own >> 20} MiB"
    )


# ---- failures leave nothing behind ---------------------------------------------------------------


def separate_dirs(tmp_path: Path) -> tuple[Path, Path]:
    inputs, outputs = tmp_path / "in", tmp_path / "out"
    inputs.mkdir()
    outputs.mkdir()
    return inputs, outputs


def test_non_finite_input_fails_cleanly(tmp_path: Path) -> None:
    inputs, outputs = separate_dirs(tmp_path)
    soup = inputs / "nan.f32"
    tris = np.random.default_rng(1).random((30_000, 3, 3)).astype(np.float32)
    tris[25_000, 1, 2] = np.nan
    tris.tofile(soup)
    seen: list[BuildProgress] = []
    # Small chunks: the bad triangle comes after several chunks have been read.
    with pytest.raises(MeshError, match=r"triangle 25000 has a non-finite coordinate"):
        build_model(soup, outputs / "m.vast", BuildOptions(memory=SMALL_MEMORY), progress=seen.append)
    assert seen and seen[-1].done > 0
    assert os.listdir(outputs) == []
    assert os.listdir(inputs) == ["nan.f32"]


def test_truncated_ply_fails_cleanly(tmp_path: Path) -> None:
    inputs, outputs = separate_dirs(tmp_path)
    ply = inputs / "cut.ply"
    scenes.write_scene("spheres", 5_000, 1, ply)
    with open(ply, "r+b") as f:
        f.truncate(ply.stat().st_size * 2 // 3)
    with pytest.raises(MeshError, match="truncated"):
        build_model(ply, outputs / "m.vast")
    assert os.listdir(outputs) == []
    result = run_cli("build", str(ply), "-o", str(outputs / "m.vast"), cwd=tmp_path)
    assert result.returncode == 2 and "vastray: error:" in result.stderr and "truncated" in result.stderr
    assert os.listdir(outputs) == []


@pytest.fixture(scope="module")
def two_level_soup(workdir: Path) -> Path:
    """A height field of 204,800 triangles: at the smallest budget its first out-of-core
    cells are still too big, so a second level is sifted in the split phase."""
    path = workdir / "inputs" / "grid.f32"
    path.parent.mkdir(exist_ok=True)
    if not path.exists():
        write_grid_soup(path, 320)
    return path


@pytest.mark.parametrize(
    ("phase", "own_scratch"),
    [("scan", False), ("read", False), ("split", False), ("build", True), ("write", False)],
)
def test_cancel_leaves_nothing_behind(
    tmp_path: Path, ooc_ply: Path, two_level_soup: Path, phase: str, own_scratch: bool
) -> None:
    outputs, scratch = tmp_path / "out", tmp_path / "scratch"
    outputs.mkdir()
    scratch.mkdir()
    source = {"split": two_level_soup, "scan": "scene:plant:30000:2"}.get(phase, ooc_ply)
    cancel = threading.Event()
    seen: list[BuildProgress] = []

    def progress(p: BuildProgress) -> None:
        seen.append(p)
        if p.phase == phase and p.done > 0:
            cancel.set()

    options = BuildOptions(memory=SMALL_MEMORY, scratch_dir=str(scratch) if own_scratch else None)
    with pytest.raises(BuildCancelledError):
        build_model(source, outputs / "m.vast", options, progress=progress, cancel=cancel)
    assert cancel.is_set() and seen[-1].phase == phase
    assert os.listdir(outputs) == []
    assert os.listdir(scratch) == []


_FULL_DISK_CHILD = """
import resource, signal, sys
from vastray.build import BuildOptions, build_model
phases = []
# Files may grow to 256 KiB, as on a full disk: a write past it fails with EFBIG (with
# SIGXFSZ ignored) instead of killing the process.
signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
resource.setrlimit(resource.RLIMIT_FSIZE, (1 << 18, 1 << 18))
try:
    options = BuildOptions(memory=int(sys.argv[3]))
    build_model(sys.argv[1], sys.argv[2], options, progress=lambda p: phases.append(p.phase))
except OSError as e:
    print(phases[-1], e.errno, e, flush=True)
"""


def test_a_failed_scratch_write_fails_the_build_cleanly(tmp_path: Path, ooc_ply: Path) -> None:
    """Out-of-core sifting writes its cells on a thread of its own: when a write fails
    (here a file-size limit, as on a full disk), the build stops in its read phase with
    the system's error, instead of hanging or writing a model, and leaves nothing behind."""
    out = tmp_path / "out"
    out.mkdir()
    result = subprocess.run(
        [sys.executable, "-c", _FULL_DISK_CHILD, str(ooc_ply), str(out / "m.vast"), str(SMALL_MEMORY)],
        cwd=tmp_path, capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert result.returncode == 0, result.stderr
    phase, code, *_ = result.stdout.split()
    assert phase == "read" and int(code) == errno.EFBIG, result.stdout
    assert "scratch write failed: File too large" in result.stdout and ".tri" in result.stdout
    assert os.listdir(out) == []


_CANCEL_CHILD = """
import sys, threading
from vastray.build import BuildCancelledError, BuildOptions, build_model
cancel = threading.Event()
def progress(p):
    if p.phase == "build" and p.done > 0:
        cancel.set()
try:
    options = BuildOptions(memory=int(sys.argv[3]))
    build_model(sys.argv[1], sys.argv[2], options, progress=progress, cancel=cancel)
except BuildCancelledError:
    print("cancelled", flush=True)
"""


def test_process_exits_cleanly_after_a_cancelled_build(tmp_path: Path, ooc_ply: Path) -> None:
    """A service that cancels a build in its build phase (the native writer running)
    goes on and later exits normally: the cancellation leaves no state behind that
    outlives the interpreter."""
    result = subprocess.run(
        [sys.executable, "-c", _CANCEL_CHILD, str(ooc_ply), str(tmp_path / "m.vast"), str(SMALL_MEMORY)],
        cwd=tmp_path, capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert result.stdout == "cancelled\n", result.stderr
    assert result.returncode == 0, f"exit status {result.returncode} after a cancelled build"
    assert os.listdir(tmp_path) == []


def read_until(stream: Any, pattern: str, buffer: list[str], found: threading.Event) -> None:
    while chunk := os.read(stream.fileno(), 4096):
        buffer.append(chunk.decode(errors="replace"))
        if pattern in "".join(buffer[-3:]):
            found.set()


@pytest.mark.timeout(120)
@pytest.mark.parametrize(
    ("signum", "phase", "delay"),
    [(signal.SIGINT, "build", 0.0), (signal.SIGINT, "build", 0.3), (signal.SIGTERM, "split", 0.0),
     (signal.SIGTERM, "build", 0.3)],
)  # fmt: skip
def test_interrupted_cli_build_leaves_nothing_behind(
    tmp_path: Path, signum: int, phase: str, delay: float
) -> None:
    """Ctrl-C (SIGINT) or SIGTERM once the phase's progress shows (and `delay` seconds
    into it): exit status 128 + signal, "interrupted", no model, partial or scratch files."""
    out = tmp_path / "plant.vast"
    proc = subprocess.Popen(
        [str(VASTRAY), "build", "scene:plant:400000:1", "-o", str(out), "--memory", "6M"],
        cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
    )  # fmt: skip
    err: list[str] = []
    found = threading.Event()
    reader = threading.Thread(target=read_until, args=(proc.stderr, f"{phase}:", err, found), daemon=True)
    reader.start()
    try:
        assert found.wait(60), f"no {phase} progress: {''.join(err)[-500:]}"
        time.sleep(delay)
        assert proc.poll() is None, "the build finished before it could be interrupted"
        proc.send_signal(signum)
        proc.wait(60)
    finally:
        proc.kill()
        proc.wait()
    reader.join(10)
    left = sorted(os.listdir(tmp_path))
    # 128 + the signal number: 130 for SIGINT, 143 for SIGTERM.
    assert proc.returncode == 128 + signum, (
        f"exit status {proc.returncode}, left {left}: {''.join(err)[-600:]}"
    )
    assert "vastray: interrupted" in "".join(err)
    assert left == []


def test_existing_output_is_kept_unless_overwriting(built: Callable[[str], Case], tmp_path: Path) -> None:
    soup = built("soup")
    out = tmp_path / "m.vast"
    shutil.copyfile(built("bunny").path, out)
    before = out.read_bytes()
    with pytest.raises(FileExistsError, match="exists"):
        build_model(soup.source, out)
    result = run_cli("build", str(soup.source), "-o", str(out), cwd=tmp_path)
    assert result.returncode == 2
    assert "vastray: error:" in result.stderr and "exists" in result.stderr and "--force" in result.stderr
    assert out.read_bytes() == before
    assert os.listdir(tmp_path) == ["m.vast"]

    report = build_model(soup.source, out, BuildOptions(overwrite=True))
    with ModelFile(out) as model:
        assert model.header["input_triangles"] == report["input_triangles"] == len(soup.corners)
    result = run_cli("build", str(built("bunny").source), "-o", str(out), "--force", cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    with ModelFile(out) as model:
        assert model.header["triangle_count"] == built("bunny").report["triangles"]
    assert os.listdir(tmp_path) == ["m.vast"]


# ---- progress ------------------------------------------------------------------------------------


@pytest.mark.parametrize("name", ["bunny", "plant", "soup", "out-of-core"])
def test_progress_phases_in_order(built: Callable[[str], Case], name: str) -> None:
    """Phases in order, each ending with done == total; the read phase counts the
    input's triangles once (a 300k-triangle input reads 300k, whatever passes the
    bounds took), and a scan's total is what it scans (bytes of a text file, triangles
    of a soup or generated scene)."""
    case = built(name)
    phases = [phase for phase, _ in groupby(case.events, key=lambda e: e.phase)]
    scan = ["scan"] if name in ("bunny", "plant", "soup") else []  # text file, generator, soup bounds
    assert phases == [*scan, "read", "build", "write"]
    elapsed = [e.elapsed for e in case.events]
    assert elapsed == sorted(elapsed)
    scan_unit = "bytes" if name == "bunny" else "triangles"
    for phase, group in groupby(case.events, key=lambda e: e.phase):
        events = list(group)
        done = [e.done for e in events]
        assert done == sorted(done), f"{phase}: done goes back: {done}"
        assert all(0 <= e.done <= e.total for e in events), phase
        unit = {"write": "bytes", "scan": scan_unit}.get(phase, "triangles")
        assert {e.unit for e in events} == {unit}, phase
        assert events[-1].done == events[-1].total > 0, phase
        if phase in ("read", "build", "write"):
            assert len({e.total for e in events}) == 1, (phase, {e.total for e in events})
    read_total = next(e.total for e in case.events if e.phase == "read")
    assert read_total == len(case.corners) == case.report["input_triangles"]
    if name == "bunny":
        assert next(e.total for e in case.events if e.phase == "scan") == Path(case.source).stat().st_size
    # The write phase copies every block, or (the blocks written in place) those it moves
    # into the room kept in front of them.
    write_total = next(e.total for e in case.events if e.phase == "write")
    copied = case.model.blocks
    if case.report["blocks_in_place"]:
        front = model_assembly.front_reserve(case.report["triangles"])
        copied = [b for b in copied if b.offset < front]
    assert write_total == sum(b.stored_size for b in copied)


# ---- command line --------------------------------------------------------------------------------


def test_cli_build_inspect_render(built: Callable[[str], Case], tmp_path: Path) -> None:
    soup = built("soup")
    out = tmp_path / "soup.vast"
    result = run_cli("build", str(soup.source), "-o", str(out), "--memory", "8M", cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    assert f"input      {len(soup.corners):,} triangles; 3 degenerate dropped" in result.stdout
    assert f"built      {out}: {len(soup.corners) - 3:,} triangles" in result.stdout
    assert sorted(os.listdir(tmp_path)) == ["soup.vast"]

    result = run_cli("inspect", str(out), cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    counts = rf"^triangles  {len(soup.corners) - 3:,} \(input {len(soup.corners):,}, 3 degenerate dropped\)"
    assert re.search(counts, result.stdout, re.M), result.stdout
    with ModelFile(out) as model:
        stats = model.stats()
        node_levels = model.node_levels
    table = re.findall(
        r"^ +(\d+|triangles) +([\d,]+) +([\d,]+) +([\d,]+) +[\d.]+ +[\d.]+ +[\d.]+$", result.stdout, re.M
    )
    assert [row[0] for row in table] == [str(i) for i in range(node_levels)] + ["triangles"]
    numbers = [[int(x.replace(",", "")) for x in row[1:]] for row in table]
    expected = [
        [lv.get("nodes", lv.get("triangle_records")), lv.get("voxels", lv.get("vertices")), lv["blocks"]]
        for lv in stats["levels"]
    ]
    assert numbers == expected

    result = run_cli("inspect", "--json", "--verify", str(out), cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    assert json.loads(result.stdout) == json.loads(json.dumps(stats))

    png = tmp_path / "soup.png"
    result = run_cli("render", str(out), "--size", "64x48", "-o", str(png), cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    assert "complete after" in result.stdout  # rendered through the block cache at full detail
    image = np.asarray(Image.open(png))
    assert image.shape == (48, 64, 3)
    assert np.any(image != image[:, :1, :], axis=2).mean() > 0.05  # the model is in view

    result = run_cli("build", str(out), "-o", str(tmp_path / "again.vast"), cwd=tmp_path)
    assert result.returncode == 2
    assert "vastray: error:" in result.stderr and "already a built model" in result.stderr
    assert sorted(os.listdir(tmp_path)) == ["soup.png", "soup.vast"]


# ---- inputs the format must hold -----------------------------------------------------------------


def test_parse_bytes(tmp_path: Path) -> None:
    assert parse_bytes("2G") == 2 << 30
    assert parse_bytes("512M") == parse_bytes("512MiB") == parse_bytes("512mb") == 512 << 20
    assert parse_bytes("1.5GiB") == 3 << 29
    assert parse_bytes("4096") == 4096
    for bad in ("", "lots", "-1G", "0", "nan", "inf"):
        with pytest.raises(ValueError, match="memory budget"):
            parse_bytes(bad, "memory budget")
    with pytest.raises(ValueError, match="memory budget too small"):
        build_model("scene:plant:1000:1", tmp_path / "m.vast", BuildOptions(memory=1 << 20))
    assert os.listdir(tmp_path) == []


@pytest.mark.parametrize(
    ("options", "message"),
    [
        ({"threads": -1}, r"threads must be 0 \(every core\) or a positive count, got -1"),
        ({"threads": 1.5}, "threads must be an integer"),
        ({"leaf_size": 0}, "leaf_size must be at least 1"),
        ({"voxel_rays": 9}, r"voxel_rays must be 1 \.\.\. 8"),
        ({"traversal_cost": float("nan")}, "traversal_cost must be a positive number"),
        ({"empty_space_ratio": 1.0}, r"empty_space_ratio must be in \[0, 1\)"),
        ({"lz4_hc_level": 13}, r"lz4_hc_level must be 0 \(fast LZ4\) \.\.\. 12, got 13"),
    ],
)
def test_bad_options_are_clear_errors_before_any_work(tmp_path: Path, options: dict, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        build_model("scene:plant:1000:1", tmp_path / "m.vast", BuildOptions(**options))
    assert os.listdir(tmp_path) == []


def test_cli_rejects_negative_threads_without_a_traceback(tmp_path: Path) -> None:
    result = run_cli("build", "demo", "-o", str(tmp_path / "d.vast"), "--threads", "-1", cwd=tmp_path)
    assert result.returncode == 2
    expected = "vastray: error: threads must be 0 (every core) or a positive count, got -1"
    assert result.stderr.strip() == expected
    assert os.listdir(tmp_path) == []


def test_traversal_cost_makes_a_coarser_smaller_tree(tmp_path: Path) -> None:
    """`--traversal-cost` reaches the kd builder: a costlier node step gives fewer leaves,
    fewer references and a smaller file of the same triangles, and a cost that is not a
    positive number is refused before any work."""
    files = {}
    for cost in (None, "8"):
        out = tmp_path / f"tc-{cost}.vast"
        extra = [] if cost is None else ["--traversal-cost", cost]
        result = run_cli("build", "scene:plant:20000:1", "-o", str(out), *extra, cwd=tmp_path)
        assert result.returncode == 0, result.stderr
        files[cost] = out
    with ModelFile(files[None]) as default, ModelFile(files["8"]) as coarse:
        assert coarse.header["triangle_count"] == default.header["triangle_count"]
        assert coarse.header["leaves"] < default.header["leaves"]
        assert coarse.header["references"] < default.header["references"]
        assert coarse.header["file_size"] < default.header["file_size"]
    for bad in ("0", "-1", "nan"):
        out = tmp_path / "bad.vast"
        result = run_cli("build", "scene:plant:2000:1", "-o", str(out), "--traversal-cost", bad, cwd=tmp_path)
        assert result.returncode == 2 and "traversal_cost must be a positive number" in result.stderr
        assert not out.exists()


def test_a_layout_names_a_set_of_options_and_flags_override_it(tmp_path: Path) -> None:
    """`--layout smallest` builds what vastray/layouts.py says (untiered, compact blocks,
    quantized vertices, the coarser tree, LZ4 HC): the same triangles in a file under half
    the balanced one's, with fewer leaves; a flag given beside it wins over the layout's
    value; an unknown layout is refused with the choices before any work."""
    from vastray.build import BuildOptions
    from vastray.layouts import LAYOUTS

    assert set(LAYOUTS) == {"balanced", "smaller", "smallest"}
    for options in LAYOUTS.values():  # every layout is a valid set of options
        BuildOptions(**options).check()
    runs = {
        "balanced": [],
        "smallest": ["--layout", "smallest"],
        "tiered": ["--layout", "smallest", "--tier-width", "1"],
    }
    said = {  # the report's layout line says what was built, overrides included
        "balanced": "balanced: tiered, plain triangle blocks, quantized splits, traversal cost 4, LZ4, "
        "voxel errors\n",
        "smallest": "smallest: untiered, compact triangle blocks, quantized splits and vertices, "
        "traversal cost 6, LZ4 HC 9, voxel errors\n",
        "tiered": "smallest: tiered, compact",
    }
    files = {}
    for name, extra in runs.items():
        files[name] = tmp_path / f"{name}.vast"
        result = run_cli("build", "scene:plant:20000:1", "-o", str(files[name]), *extra, cwd=tmp_path)
        assert result.returncode == 0, result.stderr
        assert f"layout     {said[name]}" in result.stdout, result.stdout
    with ModelFile(files["balanced"]) as balanced, ModelFile(files["smallest"]) as smallest:
        assert balanced.tiered and not balanced.compact_triangles and not balanced.quantized_vertices
        assert not smallest.tiered and smallest.compact_triangles and smallest.quantized_vertices
        assert smallest.quantized_splits
        assert smallest.header["triangle_count"] == balanced.header["triangle_count"]
        assert smallest.header["leaves"] < balanced.header["leaves"]
        assert smallest.header["file_size"] < 0.5 * balanced.header["file_size"]
        # LZ4 HC: its blocks are stored smaller than LZ4's fast compressor makes them.
        raw = [smallest.read_block(b) for b in range(len(smallest.blocks))]
        fast = sum(min(len(lz4.block.compress(r, store_size=False)), len(r)) for r in raw)
        assert sum(e.stored_size for e in smallest.blocks) < fast
    with ModelFile(files["tiered"]) as tiered:
        assert tiered.tiered and tiered.compact_triangles and tiered.quantized_vertices
    out = tmp_path / "bad.vast"
    result = run_cli("build", "scene:plant:2000:1", "-o", str(out), "--layout", "tiny", cwd=tmp_path)
    assert result.returncode == 2 and "balanced" in result.stderr and "smallest" in result.stderr
    assert not out.exists()


def test_lz4_hc_makes_smaller_blocks_of_the_same_model(tmp_path: Path) -> None:
    """`--lz4-hc-level` compresses the blocks with LZ4 HC: every block decodes to the
    bytes the fast compressor's build holds (the same model), the file is smaller, and
    the block cache renders the same frame; a level past 12 is refused before any work."""
    files = {}
    for level in ("0", "9"):
        out = tmp_path / f"hc-{level}.vast"
        args = ("build", "scene:plant:20000:1", "-o", str(out), "--lz4-hc-level", level)
        result = run_cli(*args, cwd=tmp_path)
        assert result.returncode == 0, result.stderr
        files[level] = out
    with ModelFile(files["0"]) as fast, ModelFile(files["9"]) as small:
        small.verify()
        assert len(small.blocks) == len(fast.blocks)
        for b in range(len(fast.blocks)):
            assert small.read_block(b) == fast.read_block(b)
        stored = [sum(e.stored_size for e in m.blocks) for m in (fast, small)]
        assert stored[1] < 0.97 * stored[0], stored
        assert small.header["file_size"] < fast.header["file_size"]
    frames = []
    for path in files.values():
        with OutOfCoreModel(path, make_cache(64 << 20, 1)) as model:
            camera = frame_bounds(*model.bounds, width=96, height=64)
            frames.append(model.render_complete(camera, pixels_of_error=2.0))
    np.testing.assert_array_equal(frames[0].image, frames[1].image)
    np.testing.assert_array_equal(frames[0].prim, frames[1].prim)
    out = tmp_path / "bad.vast"
    result = run_cli("build", "scene:plant:2000:1", "-o", str(out), "--lz4-hc-level", "13", cwd=tmp_path)
    assert result.returncode == 2 and "lz4_hc_level must be 0 (fast LZ4) ... 12, got 13" in result.stderr
    assert not out.exists()


def test_the_write_phase_copies_blocks_across_file_systems(tmp_path: Path, ooc_ply: Path) -> None:
    """The write phase copies the level files' blocks into the model (direct_io.py):
    with the scratch folder on another file system (a tmpfs) than the output, the same
    model, byte for byte."""
    shm = Path("/dev/shm")
    if not shm.is_dir() or shm.stat().st_dev == tmp_path.stat().st_dev or not os.access(shm, os.W_OK):
        pytest.skip("no writable file system other than the test folder's")
    options = BuildOptions(memory=SMALL_MEMORY)
    same = build_model(ooc_ply, tmp_path / "same.vast", options)
    with tempfile.TemporaryDirectory(dir=shm) as scratch:
        elsewhere = BuildOptions(memory=SMALL_MEMORY, scratch_dir=scratch)
        other = build_model(ooc_ply, tmp_path / "other.vast", elsewhere)
        assert os.listdir(scratch) == []
    assert same["blocks"] == other["blocks"] > 8
    assert (tmp_path / "same.vast").read_bytes() == (tmp_path / "other.vast").read_bytes()
    with ModelFile(tmp_path / "other.vast") as model:
        model.verify()
