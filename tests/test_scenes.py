"""Procedural scenes: counts, determinism, chunk bounds and streamed files."""

from __future__ import annotations

import os
import warnings
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import trimesh

from vastray import scenes
from vastray.scenes import (
    CHUNK_TRIANGLES,
    SCENES,
    SceneSpec,
    generate,
    to_mesh,
    write_scene,
)
from vastray.scenes._geom import (
    ChunkBuffer,
    boxes,
    cylinders,
    elbows,
    signed_volume,
    uv_sphere,
)

NAMES = sorted(SCENES)


def _collect(name: str, triangles: int, seed: int) -> list[tuple]:
    return list(generate(name, triangles, seed))


@pytest.mark.parametrize("triangles", [1_000, 10_000, 100_000])
@pytest.mark.parametrize("name", NAMES)
def test_triangle_count_close_to_request(name: str, triangles: int) -> None:
    total = 0
    for vertices, faces, colours in generate(name, triangles, seed=1):
        assert vertices.dtype == np.float64 and vertices.ndim == 2 and vertices.shape[1] == 3
        assert faces.dtype == np.uint32 and faces.ndim == 2 and faces.shape[1] == 3
        assert faces.max() < vertices.shape[0]
        assert np.isfinite(vertices).all()
        assert colours is not None and colours.dtype == np.uint8
        assert colours.shape == faces.shape
        total += faces.shape[0]
    assert abs(total / triangles - 1) <= 0.05, total


def _soup(chunks: list[tuple]) -> np.ndarray:
    return np.concatenate([v[f] for v, f, _ in chunks])


@pytest.mark.parametrize("name", NAMES)
def test_deterministic_by_seed(name: str) -> None:
    first = _collect(name, 10_000, seed=5)
    again = _collect(name, 10_000, seed=5)
    assert len(first) == len(again)
    for a, b in zip(first, again, strict=True):
        for x, y in zip(a, b, strict=True):
            assert np.array_equal(x, y)
    one, other = _soup(first), _soup(_collect(name, 10_000, seed=6))
    assert one.shape != other.shape or not np.array_equal(one, other)


@pytest.mark.parametrize("name", NAMES)
def test_scene_is_a_valid_mesh_without_degenerate_triangles(name: str) -> None:
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a DegenerateTrianglesWarning would fail here
        mesh = to_mesh(name, 20_000, seed=2)
    lo, hi = mesh.bounds()
    assert np.all(hi - lo > 1.0) and np.all(np.abs(lo) < 1e3) and np.all(np.abs(hi) < 1e3)


def test_mandelbulb_is_closed_and_outward() -> None:
    chunks = _collect("mandelbulb", 20_000, seed=3)
    assert len(chunks) == 1  # a single chunk shares its vertices
    vertices, faces, _ = chunks[0]
    mesh = trimesh.Trimesh(vertices, faces, process=False)
    assert mesh.is_watertight and mesh.is_winding_consistent
    assert mesh.volume > 1.0  # positive: normals point out


def test_primitives_wind_outward() -> None:
    v, f = boxes([[0, 0, 0]], [[1, 2, 3]])
    assert signed_volume(v, f) == pytest.approx(6.0)
    v, f = cylinders([[0, 0, 0]], [[0, 0, 2]], 1.0, 64, caps=True)
    assert signed_volume(v, f) == pytest.approx(2 * np.pi, rel=0.01)
    v, f = uv_sphere(64, 32)
    assert signed_volume(v, f) == pytest.approx(4 / 3 * np.pi, rel=0.01)
    # A bend's tube: faces point away from its centre line.
    v, f = elbows([[0, 0, 0]], [[1, 0, 0]], [[0, 1, 0]], 1.0, 0.1, 8, 4)
    c = v[f].mean(axis=1)
    n = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    spine = c * [1, 1, 0]
    spine /= np.linalg.norm(spine, axis=1, keepdims=True)
    assert (np.einsum("ij,ij->i", n, c - spine) > 0).all()


def test_pipe_bend_meets_straight_pipe_without_seam() -> None:
    # Rings of a bend and the straight pipe it joins coincide, so no cracks open.
    bend_v, _ = elbows([[0, 0, 0]], [[1, 0, 0]], [[0, 1, 0]], 0.4, 0.1, 8, 4)
    pipe_v, _ = cylinders([[0.4, -1.0, 0.0]], [[0.4, 0.0, 0.0]], 0.1, 8, caps=False)
    ring = {tuple(p) for p in np.round(bend_v[:8], 9)}
    assert ring == {tuple(p) for p in np.round(pipe_v[8:], 9)}


@pytest.mark.parametrize("name", NAMES)
def test_write_ply_round_trips_through_trimesh(name: str, tmp_path: Path) -> None:
    path = tmp_path / f"{name}.ply"
    seen: list[int] = []
    info = write_scene(name, 5_000, 4, path, progress=seen.append)
    expected = to_mesh(name, 5_000, 4)
    assert info["triangles"] == expected.triangle_count == sum(seen)
    assert info["vertices"] == expected.vertices.shape[0]
    assert info["bytes"] == path.stat().st_size
    loaded = trimesh.load(path, process=False)
    assert np.array_equal(loaded.faces, expected.faces)
    assert np.allclose(loaded.vertices, expected.vertices, atol=1e-5)
    assert loaded.visual.kind == "face"
    assert np.array_equal(loaded.visual.face_colors[:, :3], expected.face_colours)
    assert not [p for p in tmp_path.iterdir() if p != path]  # no temp files left over


def test_write_ply_without_colours(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    base = SCENES["spheres"]

    def plain(triangles: int, seed: int) -> Iterator[tuple]:
        for v, f, _ in base.generator(triangles, seed):
            yield v, f, None

    monkeypatch.setitem(SCENES, "plain", SceneSpec("plain", "test", False, plain))
    path = tmp_path / "plain.ply"
    info = write_scene("plain", 3_000, 1, path)
    loaded = trimesh.load(path, process=False)
    assert len(loaded.faces) == info["triangles"]
    assert loaded.visual.kind is None


def test_write_stl(tmp_path: Path) -> None:
    path = tmp_path / "plant.STL"
    info = write_scene("plant", 5_000, 1, path)
    expected = to_mesh("plant", 5_000, 1)
    assert info["triangles"] == expected.triangle_count
    assert path.stat().st_size == 84 + 50 * info["triangles"]
    loaded = trimesh.load(path, file_type="stl", process=False)
    assert np.allclose(loaded.vertices, expected.vertices[expected.faces].reshape(-1, 3), atol=1e-5)


def test_bad_arguments(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match=r"\.ply or \.stl"):
        write_scene("spheres", 1_000, 0, tmp_path / "x.obj")
    with pytest.raises(ValueError, match="unknown scene"):
        write_scene("teapot", 1_000, 0, tmp_path / "x.ply")
    with pytest.raises(ValueError, match="triangles"):
        next(generate("spheres", 10, 0))
    with pytest.raises(ValueError, match="seed"):
        next(generate("spheres", 1_000, -1))
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("error", [KeyboardInterrupt, RuntimeError])
@pytest.mark.parametrize("suffix", [".ply", ".stl"])
def test_interrupted_write_leaves_nothing(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, error: type[BaseException], suffix: str
) -> None:
    base = SCENES["spheres"]

    def broken(triangles: int, seed: int) -> Iterator[tuple]:
        chunks = base.generator(triangles, seed)
        yield next(chunks)
        raise error("stop")

    monkeypatch.setitem(SCENES, "broken", SceneSpec("broken", "test", True, broken))
    target = tmp_path / f"out{suffix}"
    with pytest.raises(error):
        write_scene("broken", 2_000, 0, target)
    assert list(tmp_path.iterdir()) == []

    # An existing file under the target name survives a failed rewrite untouched.
    target.write_bytes(b"previous")
    with pytest.raises(error):
        write_scene("broken", 2_000, 0, target)
    assert list(tmp_path.iterdir()) == [target]
    assert target.read_bytes() == b"previous"


@pytest.mark.parametrize("name", ["spheres", "plant"])
def test_chunks_stay_bounded_for_big_scenes(name: str) -> None:
    sizes = [faces.shape[0] for _, faces, _ in generate(name, 2_000_000, seed=0)]
    assert len(sizes) >= 2
    assert max(sizes) <= CHUNK_TRIANGLES
    assert abs(sum(sizes) / 2_000_000 - 1) <= 0.05


def test_smaller_chunk_limit_splits_without_changing_geometry(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # 2e6 mandelbulb triangles take too long for a unit test; a smaller chunk limit
    # exercises the same splitting on 1e5.
    whole = _collect("mandelbulb", 100_000, seed=0)
    monkeypatch.setattr("vastray.scenes._geom.CHUNK_TRIANGLES", 20_000)
    parts = _collect("mandelbulb", 100_000, seed=0)
    assert len(parts) >= 5
    assert max(f.shape[0] for _, f, _ in parts) <= 20_000

    assert np.array_equal(_soup(whole), _soup(parts))
    assert np.array_equal(np.concatenate([c for _, _, c in whole]), np.concatenate([c for _, _, c in parts]))


def test_chunk_buffer_splits_oversized_parts() -> None:
    buffer = ChunkBuffer(limit=100)
    v, f = uv_sphere(30, 10)  # 540 triangles in one part
    buffer.add(v, f, np.zeros((f.shape[0], 3), np.uint8))
    chunks = list(buffer.drain(final=True))
    assert [c[1].shape[0] for c in chunks] == [100] * 5 + [40]
    for vertices, faces, _ in chunks:
        assert faces.max() == vertices.shape[0] - 1  # compacted: no unused vertices
    rebuilt = np.concatenate([c[0][c[1]] for c in chunks])
    assert np.array_equal(rebuilt, v[f])


def test_registry_is_public() -> None:
    assert set(SCENES) == {"spheres", "plant", "mandelbulb"}
    assert all(spec.description for spec in SCENES.values())
    assert scenes.MIN_TRIANGLES <= 1_000


def test_mandelbulb_calibration_table_matches_fresh_counts() -> None:
    # Large requests trust the table; a change to the surface must re-measure it.
    module = __import__("vastray.scenes.mandelbulb", fromlist=["measure_calibration"])
    fresh = module.measure_calibration(12)
    assert fresh == pytest.approx(list(module._CALIBRATION[:12]), rel=0.01)


def test_written_scene_has_ordinary_file_permissions(tmp_path: Path) -> None:
    out = tmp_path / "perm.ply"
    write_scene("spheres", 2000, 1, out)
    umask = os.umask(0)
    os.umask(umask)
    assert out.stat().st_mode & 0o777 == 0o666 & ~umask


def test_a_built_plant_stores_its_systems_and_structures_as_parts(tmp_path: Path) -> None:
    """`vastray build scene:plant:...` keeps the plant's parts (pipe systems and kinds of
    structure): every triangle in one, fixed-colour structures exactly, pipes (and their
    darker flanges) by their system's hue."""
    from vastray.build import BuildOptions, build_model
    from vastray.modelfile import ModelFile
    from vastray.scenes.plant import PART_NAMES

    path = tmp_path / "plant.vast"
    build_model("scene:plant:30000:4", path, BuildOptions(memory=64 << 20))
    mesh = scenes.to_mesh("plant", 30_000, 4)
    with ModelFile(path) as model:
        parts = model.parts
        part = model.part_of(np.arange(len(mesh.faces)))
    names = {p.name for p in parts}
    assert {"steel frame", "bolts", "steam pipes"} <= names <= set(PART_NAMES)
    assert sum(p.triangles for p in parts) == len(mesh.faces) and (part >= 0).all()
    by_name = {p.name: p.id for p in parts}
    colours = mesh.face_colours.astype(float)
    assert (colours[part == by_name["steel frame"]] == (96, 108, 124)).all()
    steam = colours[part == by_name["steam pipes"]]
    hue = steam / np.linalg.norm(steam, axis=1, keepdims=True)
    reference = np.array([196, 52, 40]) / np.linalg.norm([196, 52, 40])
    assert (hue @ reference > 0.99).all() and len(steam) > 100
