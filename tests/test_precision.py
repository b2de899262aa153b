"""Quantized split planes (format version 3, FLAG_QUANTIZED_SPLITS; paper 004): a build
option whose basic nodes take 4 bytes, their split a 20-bit step of the node's cell.
The tree is built on those planes and the triangles stay exact, so the images must
equal full precision's: checked in core (the decoded scene) and out of core (through
the block cache), on a model built in core and on one split out of core. The walker
of tests/modelwalk.py reads the layout from FORMAT.md alone and must agree with the
native decoder; full-precision models still read as versions 1 and 2."""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np
import pytest
from modelwalk import dequantize, walk
from test_build import SMALL_MEMORY, rewrite_version
from views import model_views

from vastray import native
from vastray.build import BuildOptions, build_model
from vastray.modelfile import (
    FLAG_QUANTIZED_SPLITS,
    SPLIT_STEPS,
    VERSION,
    ModelError,
    ModelFile,
    dequantize_split,
    quantize_split,
)
from vastray.outofcore import OutOfCoreModel, make_cache
from vastray.renderer import trace

SOURCES = {"plant": ("scene:plant:60000:3", 2 << 30), "out-of-core": ("scene:plant:60000:2", SMALL_MEMORY)}


@pytest.fixture(scope="module")
def models(tmp_path_factory: pytest.TempPathFactory) -> dict[tuple[str, bool], Path]:
    folder = tmp_path_factory.mktemp("precision")
    out = {}
    for name, (source, memory) in SOURCES.items():
        for quantized in (False, True):
            path = folder / f"{name}-{'q' if quantized else 'f'}.vast"
            # Without voxel errors, which come with quantized splits only (their own tests:
            # test_voxel_errors.py): full and quantized take the same LOD test.
            options = BuildOptions(memory=memory, quantized_splits=quantized, voxel_errors=False)
            build_model(source, path, options)
            out[name, quantized] = path
    return out


def test_the_header_says_which(models: dict[tuple[str, bool], Path]) -> None:
    for (_, quantized), path in models.items():
        with ModelFile(path) as model:
            assert model.header["version"] == VERSION == 8
            assert bool(model.header["flags"] & FLAG_QUANTIZED_SPLITS) == quantized
            assert model.quantized_splits == quantized and model.stats()["quantized_splits"] == quantized


@pytest.mark.parametrize("name", SOURCES)
def test_same_triangles_smaller_nodes(models: dict[tuple[str, bool], Path], name: str) -> None:
    with ModelFile(models[name, False]) as full, ModelFile(models[name, True]) as small:
        assert small.header["triangle_count"] == full.header["triangle_count"]
        nodes = [
            sum(m.stats()["levels"][i]["raw_bytes"] for i in range(m.node_levels)) for m in (full, small)
        ]
        basic = small.header["basic_nodes"]
        # Each basic and each LOD node saves 4 bytes, less the padding to 8 bytes that
        # some treelets take back (at most 4 bytes each).
        assert nodes[0] - nodes[1] > 2 * basic + small.header["lod_nodes"] > 0
        assert small.header["file_size"] < full.header["file_size"]
        a, b = full.to_scene(), small.to_scene()
        assert a.triangle_count == b.triangle_count


def test_the_walker_agrees(models: dict[tuple[str, bool], Path]) -> None:
    """Every split of the walker's reading lies inside its cell, and its leaves hold every
    kept triangle, each inside (or cut by) the leaf's cell."""
    for name in SOURCES:
        with ModelFile(models[name, True]) as model:
            ids: set[int] = set()
            basic = 0
            for node in walk(model):
                if node.kind == "leaf":
                    assert node.ids is not None and node.vertices is not None
                    ids.update(node.ids.tolist())
                    tri_lo, tri_hi = node.vertices.min(axis=1), node.vertices.max(axis=1)
                    assert (tri_lo <= node.hi).all() and (tri_hi >= node.lo).all()
                    continue
                assert node.lo[node.axis] < node.split < node.hi[node.axis]
                basic += node.kind == "basic"
                if node.kind == "lod":  # derived from the cell, as the writer computed it
                    ext = (node.hi - node.lo).astype(np.float64)
                    assert node.radius == pytest.approx(0.5 * np.sqrt(ext @ ext), rel=1e-6)
            assert basic == model.header["basic_nodes"]
            assert len(ids) == model.header["triangle_count"]


def test_images_are_identical(models: dict[tuple[str, bool], Path]) -> None:
    """Full detail, in core and out of core: the same depth at every pixel, and the same
    triangle wherever two triangles do not tie for the nearest hit."""
    for name in SOURCES:
        full, small = models[name, False], models[name, True]
        for camera in model_views(full, (64, 48)):
            frames = []
            for path in (full, small):
                with ModelFile(path) as model:
                    frames.append(trace(model.to_scene(), camera))
                with OutOfCoreModel(path, make_cache(64 << 20, 1)) as ooc:
                    frames.append(ooc.render_complete(camera, pixels_of_error=0.0))
            reference = frames[0]
            assert (reference.prim >= 0).sum() > 500
            for frame in frames[1:]:
                np.testing.assert_array_equal(frame.depth, reference.depth)
                assert (frame.prim != reference.prim).mean() < 1e-3
                np.testing.assert_array_equal(frame.image, reference.image)


def test_old_versions_still_read(models: dict[tuple[str, bool], Path], tmp_path: Path) -> None:
    # A model without parts (the plant has them, and version 1 had no parts section),
    # untiered (the layout of versions 1-4).
    full = tmp_path / "spheres.vast"
    options = BuildOptions(tier_width=0, quantized_splits=False, packed_voxels=False)
    build_model("scene:spheres:20000:3", full, options)
    camera = model_views(full, (64, 48))[0]
    with ModelFile(full) as model:
        reference = trace(model.to_scene(), camera)
    for version in (1, 2):
        copy = tmp_path / f"v{version}.vast"
        copy.write_bytes(full.read_bytes())
        rewrite_version(copy, version)  # versions 1 and 2 are version 3 without the flag
        with ModelFile(copy) as model:
            assert model.header["version"] == version and not model.quantized_splits
            np.testing.assert_array_equal(trace(model.to_scene(), camera).prim, reference.prim)
        with OutOfCoreModel(copy, make_cache(64 << 20, 1)) as ooc:
            np.testing.assert_array_equal(
                ooc.render_complete(camera, pixels_of_error=0.0).prim, reference.prim
            )
    # A quantized model cannot pass for version 2: that version has no such flag.
    copy = tmp_path / "q2.vast"
    copy.write_bytes(models["plant", True].read_bytes())
    rewrite_version(copy, 2)
    with pytest.raises(ModelError, match="unsupported attribute flags"):
        ModelFile(copy)
    with pytest.raises(ModelError, match="unsupported attribute flags"):
        OutOfCoreModel(copy, make_cache(1 << 20, 1))


def test_dequantization_is_one_formula() -> None:
    """modelfile's and the walker's readings of FORMAT.md §8 agree, stay in the cell, are
    monotone in the step, and quantize_split lands strictly inside."""
    rng = np.random.default_rng(4)
    cells = [
        (-1.0, 1.0),
        (0.0, 1e-30),
        (-3e38, 3e38),
        (1.0, float(np.nextafter(np.float32(1), np.float32(2)))),
    ]
    for _ in range(200):
        a, b = np.sort(rng.normal(size=2) * 10.0 ** rng.integers(-6, 6, size=2)).astype(np.float32)
        cells.append((float(a), float(b)))
    for lo, hi in cells:
        lo, hi = float(np.float32(lo)), float(np.float32(hi))
        steps = [1, 2, SPLIT_STEPS // 3, SPLIT_STEPS // 2, SPLIT_STEPS - 2, SPLIT_STEPS - 1]
        values = [dequantize_split(lo, hi, q) for q in steps]
        assert values == [dequantize(lo, hi, q) for q in steps]
        assert all(lo <= v <= hi for v in values) and values == sorted(values)
        target = float(np.float32(lo + 0.37 * (hi - lo)))
        s = quantize_split(lo, hi, target)
        if hi - lo > 1e-6 * max(abs(lo), abs(hi)):
            assert s is not None
        if s is not None:
            assert lo < s < hi


def test_frame_counters_and_the_cli(models: dict[tuple[str, bool], Path], tmp_path: Path) -> None:
    """Node visits and triangle tests per ray are counted for both (the measure of paper
    004's extra work); `vastray build --quantized-splits` writes the flag."""
    camera = model_views(models["plant", False], (64, 48))[0]
    counts = []
    for quantized in (False, True):
        with OutOfCoreModel(models["plant", quantized], make_cache(64 << 20, 1)) as ooc:
            stats = ooc.render_complete(camera, pixels_of_error=0.0).stats
            counts.append((stats.node_visits, stats.triangle_tests))
    assert all(v > 0 and t > 0 for v, t in counts)
    # Level of detail: a quantized model's LOD nodes derive their radius from the cell;
    # with the same cells as full precision it stops at about as many voxels, and the
    # picture stays close (the trees differ a little, so not exactly).
    lod = []
    for quantized in (False, True):
        with OutOfCoreModel(models["plant", quantized], make_cache(64 << 20, 1)) as ooc:
            lod.append(ooc.render_complete(camera, pixels_of_error=3.0))
    voxels = [f.stats.voxel_hits for f in lod]
    assert voxels[0] > 100 and 0.8 < voxels[1] / voxels[0] < 1.25, voxels
    diff = np.abs(lod[0].image.astype(np.int16) - lod[1].image.astype(np.int16)).mean()
    assert diff < 3.0, diff
    from test_build import run_cli

    out = tmp_path / "cli.vast"
    result = run_cli("build", "scene:plant:3000:1", "-o", str(out), "--quantized-splits", cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    flags = struct.unpack_from("<I", out.read_bytes(), 16)[0]
    assert flags & FLAG_QUANTIZED_SPLITS
    result = run_cli("inspect", str(out), cwd=tmp_path)
    assert "quantized splits" in result.stdout, result.stdout
    assert native.FORMAT["split_bits"] == 20


def test_quantized_output_does_not_depend_on_the_thread_count(tmp_path: Path) -> None:
    """A part big enough for parallel emission (>= 2^19 references) and a parallel kd
    build: one thread and two write the same bytes."""
    files = []
    for threads in (1, 2):
        path = tmp_path / f"t{threads}.vast"
        options = BuildOptions(threads=threads, quantized_splits=True)
        report = build_model("scene:plant:200000:3", path, options)
        assert report["references"] >= 1 << 19
        files.append(path.read_bytes())
    assert files[0] == files[1]
