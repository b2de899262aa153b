"""Quantized watertight vertices (FLAG_QUANTIZED_VERTICES; paper 004, FORMAT.md §11): a
build option that snaps every vertex to a 2^21-step grid of the root cell before the tree
is built and stores each triangle block's vertices as bit-packed offsets from a block
origin. It is lossy, so the tests bound the loss against full precision from the same
input (depth within the grid step, few pixels on another triangle), check that a vertex
decodes to the same float32 in every block that stores it and that closed meshes stay
closed (rays at vertices and edges never leak), that the walker of tests/modelwalk.py
(from FORMAT.md alone) decodes what the native reader decodes, and that models without
the flag read as before."""

from __future__ import annotations

import os
import struct
from pathlib import Path

import numpy as np
import pytest
from modelwalk import grid_step, walk
from test_build import SMALL_MEMORY, rewrite_version
from test_watertight import COS_MARGIN, unique_edges
from views import model_views

from vastray import native
from vastray.build import BuildOptions, build_model
from vastray.modelfile import (
    FLAG_QUANTIZED_SPLITS,
    FLAG_QUANTIZED_VERTICES,
    ModelError,
    ModelFile,
    vertex_grid_steps,
)
from vastray.outofcore import OutOfCoreModel, make_cache
from vastray.renderer import trace

# The real meshes are part of the bar (tests/conftest.py): a missing one fails the build.
MODELS = Path(os.environ.get("VASTRAY_MODELS") or Path(__file__).resolve().parents[2] / "shared" / "models")
SOURCES = {
    "plant": ("scene:plant:60000:3", 2 << 30),
    "out-of-core": ("scene:plant:60000:2", SMALL_MEMORY),
    "fandisk": (str(MODELS / "fandisk.obj"), 2 << 30),
}
KINDS = {"full": {"quantized_splits": False},
         "vertices": {"quantized_vertices": True, "quantized_splits": False},
         "both": {"quantized_vertices": True, "quantized_splits": True}}  # fmt: skip


@pytest.fixture(scope="module")
def models(tmp_path_factory: pytest.TempPathFactory) -> dict[tuple[str, str], Path]:
    folder = tmp_path_factory.mktemp("qverts")
    out = {}
    for name, (source, memory) in SOURCES.items():
        for kind, options in KINDS.items():
            path = folder / f"{name}-{kind}.vast"
            build_model(source, path, BuildOptions(memory=memory, **options))
            out[name, kind] = path
    return out


def test_the_header_says_which_and_the_file_is_smaller(models: dict[tuple[str, str], Path]) -> None:
    for (name, kind), path in models.items():
        with ModelFile(path) as model:
            assert model.quantized_vertices == (kind != "full") == model.stats()["quantized_vertices"]
            assert bool(model.header["flags"] & FLAG_QUANTIZED_SPLITS) == (kind == "both")
            if kind != "full":
                with ModelFile(models[name, "full"]) as full:
                    assert model.header["file_size"] < full.header["file_size"]
                    assert model.header["raw_bytes"] < 0.95 * full.header["raw_bytes"]


def test_grid_step_is_one_formula() -> None:
    """modelfile's (native) and the walker's readings of FORMAT.md §11 agree: a power of
    two with 2^20 steps just past max(|lo|, |hi|)."""
    rng = np.random.default_rng(7)
    cells = [(-1.0, 1.0), (-0.5, 0.5), (0.0, 0.0), (-3e38, 3e38), (-1e-30, 2e-30)]
    for _ in range(300):
        a, b = np.sort(rng.normal(size=2) * 10.0 ** rng.integers(-8, 8, size=2)).astype(np.float32)
        cells.append((float(a), float(b)))
    for lo, hi in cells:
        steps = vertex_grid_steps([lo] * 3, [hi] * 3)
        assert steps[0] == grid_step(lo, hi)
        m = max(abs(lo), abs(hi))
        s = steps[0]
        assert np.log2(s) == int(np.log2(s)) and s * 2**20 > m and (s == 2.0**-126 or s * 2**19 <= m)


def decoded_triangles(model: ModelFile) -> dict[int, list[np.ndarray]]:
    """Every stored copy of each triangle's corners (float32), as the walker reads them."""
    copies: dict[int, list[np.ndarray]] = {}
    for node in walk(model):
        if node.kind == "leaf":
            assert node.ids is not None and node.vertices is not None
            for i, v in zip(node.ids.tolist(), node.vertices, strict=True):
                copies.setdefault(i, []).append(v)
    return copies


@pytest.mark.parametrize("name", ["plant", "out-of-core"])
def test_walker_and_native_decode_the_same(models: dict[tuple[str, str], Path], name: str) -> None:
    """The walker (its own grid step and unpacking) and the native decoder give the same
    float32 corners; every copy of a triangle in every block decodes alike (the shared
    vertex is one formula wherever it is stored); every corner lies on the grid."""
    for kind in ("vertices", "both"):
        with ModelFile(models[name, kind]) as model:
            copies = decoded_triangles(model)
            assert len(copies) == model.header["triangle_count"]
            scene = model.to_scene()
            native_corners = scene.local_vertices
            steps = np.asarray(
                vertex_grid_steps(model.header["cell_lo"], model.header["cell_hi"]), np.float64
            )
            across = 0
            for i, vs in copies.items():
                for v in vs[1:]:
                    np.testing.assert_array_equal(v, vs[0])
                across += len(vs) > 1
                np.testing.assert_array_equal(native_corners[i], vs[0])
                k = vs[0].astype(np.float64) / steps
                assert (k == np.round(k)).all() and (np.abs(k) < 2**20).all()
            assert across > 100  # triangles stored in several blocks were compared


def test_images_within_the_grid_step(models: dict[tuple[str, str], Path]) -> None:
    """Against full precision from the same input: where both hit, the depth differs by at
    most the distance a snapped triangle can move (sqrt(3) grid steps, the steps of the
    coarsest axis; a pixel on a silhouette or a crease can see another surface: those
    are counted, at most 1 % of the hit pixels); in core and out of core agree exactly."""
    for name in SOURCES:
        if (name, "full") not in models:
            continue
        full = models[name, "full"]
        with ModelFile(full) as m:
            step = max(vertex_grid_steps(m.header["cell_lo"], m.header["cell_hi"]))
        for kind in ("vertices", "both"):
            for camera in model_views(full):
                with ModelFile(full) as m:
                    a = trace(m.to_scene(), camera)
                with ModelFile(models[name, kind]) as m:
                    b = trace(m.to_scene(), camera)
                with OutOfCoreModel(models[name, kind], make_cache(64 << 20, 1)) as ooc:
                    c = ooc.render_complete(camera, pixels_of_error=0.0)
                np.testing.assert_array_equal(c.depth, b.depth)
                np.testing.assert_array_equal(c.prim, b.prim)
                both = np.isfinite(a.depth) & np.isfinite(b.depth)
                hit = np.isfinite(a.depth) | np.isfinite(b.depth)
                assert both.sum() > 500
                err = np.abs(a.depth[both] - b.depth[both])
                near = err <= np.sqrt(3) * step * 1.01 + 1e-6 * np.abs(a.depth[both])
                off = int((~near).sum() + (hit & ~both).sum())
                assert off <= 0.01 * both.sum(), (name, kind, off, both.sum(), float(err.max()), step)
                assert (a.prim[both] == b.prim[both]).mean() > 0.97


def test_closed_mesh_stays_closed(models: dict[tuple[str, str], Path]) -> None:
    """The quantized fandisk as stored (decoded by the walker, vertices merged by their
    exact float32) is still closed, and rays from outside at the midpoint and random
    points of every edge hit the stored tree (the decoded scene: the file's tree and
    vertices). Targets whose two triangles the ray would graze (|cos| < COS_MARGIN on
    either) are left out, as in test_watertight."""
    with ModelFile(models["fandisk", "vertices"]) as model:
        copies = decoded_triangles(model)
        scene = model.to_scene()
        centre = np.asarray(model.header["centre"])
    tris = np.stack([vs[0] for _, vs in sorted(copies.items())]).astype(np.float64) + centre
    vertices, inverse = np.unique(tris.reshape(-1, 3), axis=0, return_inverse=True)
    faces = inverse.reshape(-1, 3).astype(np.uint32)
    edges, counts, _ = unique_edges(faces)
    assert (counts == 2).all()  # snapping kept every edge shared by exactly two triangles
    around: dict[tuple[int, int], list[int]] = {}
    for f, (a, b, c) in enumerate(faces.tolist()):
        for u, v in ((a, b), (b, c), (c, a)):
            around.setdefault((min(u, v), max(u, v)), []).append(f)
    pair = np.array([around[a, b] for a, b in edges.tolist()])
    tri = vertices[faces.astype(np.int64)]
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    lo, hi = vertices.min(axis=0), vertices.max(axis=0)
    mid, diag = (lo + hi) / 2, float(np.linalg.norm(hi - lo))
    rng = np.random.default_rng(3)
    shot = leaks = 0
    for s in (np.full(len(edges), 0.5), rng.random(len(edges)), rng.random(len(edges))):
        p0, p1 = vertices[edges[:, 0]], vertices[edges[:, 1]]
        targets = p0 + s[:, None] * (p1 - p0)
        sphere = rng.normal(size=(len(targets), 3))
        sphere /= np.linalg.norm(sphere, axis=1, keepdims=True)
        origins = mid + 2.0 * diag * sphere
        d = targets - origins
        cos = np.einsum("nkj,nj->nk", normal[pair], d / np.linalg.norm(d, axis=1)[:, None])
        ok = (cos.min(axis=1) >= COS_MARGIN) | (cos.max(axis=1) <= -COS_MARGIN)
        hit = scene.intersect(origins[ok], d[ok])
        slack = 1e-4 * diag / np.linalg.norm(d[ok], axis=1)
        leaks += int(((hit["prim"] < 0) | (hit["t"] > 1 + slack)).sum())
        shot += int(ok.sum())
    assert shot > 10_000
    assert leaks == 0, f"{leaks} of {shot} rays leaked"


def test_old_files_still_read(tmp_path: Path, models: dict[tuple[str, str], Path]) -> None:
    """A model without the flag (and untiered: the layout versions 1-4 had), read as
    versions 1-3, renders as before; a quantized model cannot pass for version 3 (the
    flag came with version 4); the flag's absence keeps word 3 ignored."""
    full = tmp_path / "spheres.vast"
    build_model("scene:spheres:20000:3", full, BuildOptions(tier_width=0, quantized_splits=False))
    camera = model_views(full)[0]
    with ModelFile(full) as model:
        assert not model.quantized_vertices
        reference = trace(model.to_scene(), camera)
    for version in (1, 2, 3):
        copy = tmp_path / f"v{version}.vast"
        copy.write_bytes(full.read_bytes())
        rewrite_version(copy, version)
        with ModelFile(copy) as model:
            np.testing.assert_array_equal(trace(model.to_scene(), camera).prim, reference.prim)
        with OutOfCoreModel(copy, make_cache(64 << 20, 1)) as ooc:
            np.testing.assert_array_equal(
                ooc.render_complete(camera, pixels_of_error=0.0).prim, reference.prim
            )
    copy = tmp_path / "q3.vast"
    copy.write_bytes(models["plant", "vertices"].read_bytes())
    rewrite_version(copy, 3)
    with pytest.raises(ModelError, match="unsupported attribute flags"):
        ModelFile(copy)
    with pytest.raises(ModelError, match="unsupported attribute flags"):
        OutOfCoreModel(copy, make_cache(1 << 20, 1))


def test_cli_and_thread_count(tmp_path: Path) -> None:
    """`vastray build --quantized-vertices` writes the flag and `inspect` says so; one
    thread and two write the same bytes (a part big enough for parallel emission)."""
    from test_build import run_cli

    out = tmp_path / "cli.vast"
    result = run_cli("build", "scene:plant:3000:1", "-o", str(out), "--quantized-vertices", cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    assert struct.unpack_from("<I", out.read_bytes(), 16)[0] & FLAG_QUANTIZED_VERTICES
    result = run_cli("inspect", str(out), cwd=tmp_path)
    assert "quantized vertices" in result.stdout, result.stdout
    assert native.FORMAT["flag_quantized_vertices"] == 1 << 4
    files = []
    for threads in (1, 2):
        path = tmp_path / f"t{threads}.vast"
        report = build_model(
            "scene:plant:200000:3", path, BuildOptions(threads=threads, quantized_vertices=True)
        )
        assert report["references"] >= 1 << 19
        files.append(path.read_bytes())
    assert files[0] == files[1]
