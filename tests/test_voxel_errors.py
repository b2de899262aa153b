"""Voxel errors (format version 8, FLAG_VOXEL_ERRORS, docs/FORMAT.md §8 and §15): a LOD
node of a model with quantized splits stores its split as a step of its cell and, beside
it, an error code; its LOD test compares e = R * (code + 1) / 256 instead of its radius R.
The writer codes an upper bound on how far the voxel's box surface lies from the triangles
of the node's subtree (writer/voxel_errors.h), floored at a fraction of R.

Checked here: the bound against a float64 brute force over points of the box surfaces and
every triangle below (an algorithm of its own: the plane inside the triangle, else the
nearest edge); the same tree and full-detail frames as a build without errors; a floor
of 1 codes every node as its radius and gives the same frames at every PoE; the coarser
cut it is for; and the flag's refusals in every reader, and a damaged LOD word 1's."""

from __future__ import annotations

import functools
import struct
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from modelwalk import Node, Walker, WalkError
from test_build import SMALL_MEMORY, rewrite_version, run_cli
from test_compact_triangles import replace_block
from test_packed_voxels import complete_frames
from test_tiers import refused, rewrite_header

from vastray import native
from vastray.build import BuildOptions, build_model
from vastray.modelfile import FLAG_QUANTIZED_SPLITS, FLAG_VOXEL_ERRORS, VERSION, ModelError, ModelFile

SOURCES = {
    # Pipes, beams and gratings: long thin cells, whose boxes lie close to their triangles.
    "plant": ("scene:plant:60000:3", 2 << 30),
    # Parts built in core below out-of-core treelets: their errors come up through them.
    "out-of-core": ("scene:plant:60000:2", SMALL_MEMORY),
}
Built = dict[str, Path]  # "errors", "radius" (voxel_errors=False), "floor1" (voxel_error_floor=1)


@pytest.fixture(scope="module")
def built(tmp_path_factory: pytest.TempPathFactory) -> Callable[[str], Built]:
    folder = tmp_path_factory.mktemp("errors")

    @functools.cache
    def get(name: str) -> Built:
        source, memory = SOURCES[name]
        variants = {"errors": {}, "radius": {"voxel_errors": False}, "floor1": {"voxel_error_floor": 1.0}}
        paths = {}
        for variant, options in variants.items():
            paths[variant] = folder / f"{name}-{variant}.vast"
            build_model(source, paths[variant], BuildOptions(memory=memory, **options))
        return paths

    return get


def nodes(path: Path) -> list[Node]:
    with ModelFile(path) as model:
        return list(Walker(model).walk())


# ---- an independent distance: float64, by projection and edges ---------------------------------


def distances(points: np.ndarray, tris: np.ndarray) -> np.ndarray:
    """(p,) distance from each of `points` (p, 3) to the nearest of `tris` (t, 3, 3): the
    distance to the plane where the point's projection falls inside a triangle, else to
    the nearest of its three edges as segments."""
    p = points[:, None, :]  # (p, 1, 3)
    a, b, c = (tris[None, :, i, :] for i in range(3))  # (1, t, 3)
    n = np.cross(b - a, c - a)
    nn = np.einsum("...i,...i", n, n)
    inside = nn > 0
    for u, v in ((a, b), (b, c), (c, a)):
        inside = inside & (np.einsum("...i,...i", np.cross(v - u, p - u), n) >= 0)
    plane = np.abs(np.einsum("...i,...i", p - a, n)) / np.sqrt(np.where(nn > 0, nn, 1.0))
    best = np.full(inside.shape, np.inf)
    for u, v in ((a, b), (b, c), (c, a)):
        e = v - u
        ee = np.einsum("...i,...i", e, e)
        t = np.clip(np.einsum("...i,...i", p - u, e) / np.where(ee > 0, ee, 1.0), 0.0, 1.0)
        q = u + t[..., None] * e
        best = np.minimum(best, np.linalg.norm(p - q, axis=-1))
    return np.where(inside, plane, best).min(axis=1)


def surface_points(lo: np.ndarray, hi: np.ndarray, k: int = 5) -> np.ndarray:
    """A k x k grid on each face of the box [lo, hi], corners and edges included."""
    s = np.linspace(0.0, 1.0, k)
    u, v = (x.ravel() for x in np.meshgrid(s, s))
    out = []
    for axis in range(3):
        a1, a2 = (axis + 1) % 3, (axis + 2) % 3
        for side in (lo[axis], hi[axis]):
            pts = np.empty((u.size, 3))
            pts[:, axis] = side
            pts[:, a1] = lo[a1] + u * (hi[a1] - lo[a1])
            pts[:, a2] = lo[a2] + v * (hi[a2] - lo[a2])
            out.append(pts)
    return np.concatenate(out)


def test_the_distance_is_right() -> None:
    tri = np.array([[[0.0, 0.0, 0.0], [2.0, 0.0, 0.0], [0.0, 2.0, 0.0]]])
    points = np.array(
        [[0.5, 0.5, 3.0], [-1.0, -1.0, 0.0], [3.0, 0.0, 4.0], [1.0, -2.0, 0.0], [2.0, 2.0, 0.0]]
    )
    np.testing.assert_allclose(distances(points, tri), [3.0, np.sqrt(2.0), np.sqrt(17.0), 2.0, np.sqrt(2.0)])


# ---- the bound ----------------------------------------------------------------------------------


@pytest.mark.parametrize("name", list(SOURCES))
def test_the_error_bounds_the_distance_from_the_box_to_its_triangles(
    built: Callable[[str], Built], name: str
) -> None:
    walked = nodes(built(name)["errors"])
    lods = [n for n in walked if n.kind == "lod"]
    below = [n for n in lods if n.error < n.radius]
    # It is what the file is for: a good share of the voxels stand in early.
    assert len(below) > 0.1 * len(lods), (len(below), len(lods))
    assert all(n.error <= n.radius for n in lods)
    leaves = [n for n in walked if n.kind == "leaf" and n.vertices is not None and len(n.vertices)]
    leaf_lo = np.array([n.lo for n in leaves], dtype=np.float64)
    leaf_hi = np.array([n.hi for n in leaves], dtype=np.float64)
    # The subtree of a LOD node is the leaves whose cells lie in its cell (kd cells nest,
    # and cells outside it share at most a face with it).
    rng = np.random.default_rng(5)
    checked = 0
    worst = 0.0
    for i in rng.permutation(len(below)):
        node = below[i]
        lo, hi = node.lo.astype(np.float64), node.hi.astype(np.float64)
        inside = np.all((leaf_lo >= lo) & (leaf_hi <= hi), axis=1)
        tris = np.concatenate([leaves[j].vertices for j in np.flatnonzero(inside)]).astype(np.float64)
        if len(tris) > 3000:
            continue  # high in the tree: the brute force would take long; the lower ones cover it
        d = distances(surface_points(lo, hi), tris).max()
        assert d <= node.error * (1 + 1e-6), (node.level, node.depth, d, node.error, node.radius)
        worst = max(worst, d / node.error)
        checked += 1
        if checked == 150:
            break
    assert checked == 150
    assert worst > 0.2  # the bound is not loose everywhere: some surface point comes near it


# ---- what does not change -----------------------------------------------------------------------


@pytest.mark.parametrize("name", list(SOURCES))
def test_the_same_tree_as_without_errors(built: Callable[[str], Built], name: str) -> None:
    b = built(name)
    with ModelFile(b["errors"]) as e, ModelFile(b["radius"]) as r:
        assert e.header["version"] == r.header["version"] == VERSION == 8
        assert e.voxel_errors and e.header["flags"] & FLAG_VOXEL_ERRORS
        assert not r.voxel_errors and r.quantized_splits and r.packed_treelets
        assert e.stats()["voxel_errors"] and not r.stats()["voxel_errors"]
    x, y, f = nodes(b["errors"]), nodes(b["radius"]), nodes(b["floor1"])
    assert len(x) == len(y) == len(f) > 1000
    for p, q, s in zip(x, y, f, strict=True):
        assert (p.kind, p.level, p.depth, p.axis, p.empty) == (q.kind, q.level, q.depth, q.axis, q.empty)
        np.testing.assert_array_equal(p.lo, q.lo)
        np.testing.assert_array_equal(p.hi, q.hi)
        assert p.split == q.split  # the step in word 1 decodes to the same plane
        if p.kind == "lod":
            assert p.samples == q.samples and p.radius == q.radius == q.error
            assert s.error == s.radius == p.radius  # a floor of 1: every code is 255
        if p.kind == "leaf":
            np.testing.assert_array_equal(p.ids, q.ids)
            np.testing.assert_array_equal(p.vertices, q.vertices)


@pytest.mark.parametrize("name", list(SOURCES))
def test_frames(built: Callable[[str], Built], name: str) -> None:
    """Full detail is the same; a floor of 1 is the same at every PoE; errors give a coarser
    cut: more voxels, fewer triangle tests, no more memory."""
    b = built(name)
    shadings = ("headlight", "sun")
    frames = {v: complete_frames(b[v], shadings) for v in ("errors", "radius", "floor1")}
    for x, y in zip(frames["floor1"], frames["radius"], strict=True):
        np.testing.assert_array_equal(x.image, y.image)
        np.testing.assert_array_equal(x.prim, y.prim)
        np.testing.assert_array_equal(x.depth, y.depth)
    # complete_frames: PoE 8, 2 and 0, each in both shadings.
    for x, y in zip(frames["errors"][-2:], frames["radius"][-2:], strict=True):
        np.testing.assert_array_equal(x.image, y.image)
        np.testing.assert_array_equal(x.prim, y.prim)
    for x, y in zip(frames["errors"][:2], frames["radius"][:2], strict=True):  # PoE 8
        assert x.stats.voxel_hits > y.stats.voxel_hits
        assert x.stats.triangle_tests < y.stats.triangle_tests
        assert x.stats.working_set_bytes <= y.stats.working_set_bytes
    with ModelFile(b["errors"]) as model:
        full = model.to_scene()
    with ModelFile(b["radius"]) as model:
        assert full.triangle_count == model.to_scene().triangle_count


# ---- the flag -----------------------------------------------------------------------------------


def test_the_flag_is_refused_where_it_cannot_be(built: Callable[[str], Built], tmp_path: Path) -> None:
    errors = built("plant")["errors"]
    flags = ModelFile(errors).header["flags"]
    # Version 7 had no such flag.
    old = tmp_path / "v7.vast"
    old.write_bytes(errors.read_bytes())
    rewrite_version(old, 7)
    refused(old, "unsupported attribute flags")
    # The split step needs quantized splits.
    alone = tmp_path / "alone.vast"
    alone.write_bytes(errors.read_bytes())
    rewrite_header(alone, flags=flags & ~FLAG_QUANTIZED_SPLITS & ~(1 << 7))
    refused(alone, "voxel errors flag set without quantized splits")
    with pytest.raises(ValueError, match="voxel errors need quantized splits"):
        native.decode_model([], [], [0.0] * 3, [0.0] * 3, [1.0] * 3, 1, False, False, voxel_errors=True)
    with ModelFile(errors) as model:  # the walker's own check, past the reader's
        model.header["flags"] &= ~FLAG_QUANTIZED_SPLITS & ~(1 << 7)
        with pytest.raises(WalkError, match="voxel errors without quantized splits"):
            next(iter(Walker(model).walk()))
    with pytest.raises(ValueError, match="voxel_error_floor"):
        BuildOptions(voxel_error_floor=1.5).check()


def test_the_cli(tmp_path: Path) -> None:
    on, off = tmp_path / "on.vast", tmp_path / "off.vast"
    assert run_cli("build", "scene:plant:3000:1", "-o", str(on), cwd=tmp_path).returncode == 0
    result = run_cli("build", "scene:plant:3000:1", "-o", str(off), "--no-voxel-errors", cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    said = run_cli("inspect", str(on), cwd=tmp_path).stdout
    assert "voxel errors" in said, said
    assert "voxel errors" not in run_cli("inspect", str(off), cwd=tmp_path).stdout
    with ModelFile(on) as a, ModelFile(off) as b:
        assert a.voxel_errors and not b.voxel_errors


def test_a_damaged_split_word_is_refused(built: Callable[[str], Built], tmp_path: Path) -> None:
    """Bits above the error code set in a LOD node's word 1: the full decoder and the
    walker say so instead of reading a split off the grid."""
    errors = built("plant")["errors"]
    lod = next(n for n in nodes(errors) if n.kind == "lod")
    with ModelFile(errors) as model:
        raw = bytearray(model.read_block(lod.block))
    word1 = struct.unpack_from("<I", raw, lod.offset + 4)[0]
    struct.pack_into("<I", raw, lod.offset + 4, word1 | 1 << 28)
    damaged = tmp_path / "damaged.vast"
    replace_block(errors, damaged, lod.block, bytes(raw))
    with ModelFile(damaged) as model, pytest.raises(ModelError, match="LOD split word out of range"):
        model.to_scene()
    with ModelFile(damaged) as model, pytest.raises(WalkError, match=r"LOD split word .* out of range"):
        for _ in Walker(model).walk():
            pass
