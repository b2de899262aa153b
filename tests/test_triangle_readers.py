"""Streaming triangle readers against trimesh's loader on the same files, bounded chunks
and clear errors (tests/test_corpus.py covers every format and variant)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import trimesh

from vastray.mesh import MeshError
from vastray.scenes import write_scene
from vastray.triangle_readers import open_triangles


def collect(path: Path, size: int) -> tuple[np.ndarray, np.ndarray | None, int]:
    source = open_triangles(path)
    chunks = list(source.chunks(size))
    corners = np.concatenate([c.corners for c in chunks])
    colours = None if chunks[0].colours is None else np.concatenate([c.colours for c in chunks])
    assert max(len(c.corners) for c in chunks) <= size
    assert len(corners) == source.triangle_count
    return corners, colours, len(chunks)


@pytest.mark.parametrize("ext", [".ply", ".stl"])
def test_scene_files_stream_like_trimesh_loads_them(tmp_path: Path, ext: str) -> None:
    path = tmp_path / f"plant{ext}"
    write_scene("plant", 20_000, 3, path)
    corners, colours, n_chunks = collect(path, 4096)
    assert n_chunks > 1
    mesh = trimesh.load(path, process=False, force="mesh")
    np.testing.assert_array_equal(corners, np.asarray(mesh.vertices)[np.asarray(mesh.faces)])
    if ext == ".ply":
        assert colours is not None
        np.testing.assert_array_equal(colours, np.asarray(mesh.visual.face_colors)[:, :3])
    else:
        assert colours is None


def test_big_endian_ply_with_extra_properties(tmp_path: Path) -> None:
    rng = np.random.default_rng(2)
    verts = rng.normal(size=(50, 3))
    faces = rng.integers(0, 50, size=(80, 3))
    header = (
        b"ply\nformat binary_big_endian 1.0\nelement vertex 50\nproperty double x\nproperty double y\n"
        b"property double z\nproperty float confidence\nelement face 80\n"
        b"property list uchar int vertex_indices\nproperty int part\nend_header\n"
    )
    vrec = np.zeros(50, dtype=[("x", ">f8"), ("y", ">f8"), ("z", ">f8"), ("c", ">f4")])
    vrec["x"], vrec["y"], vrec["z"] = verts.T
    frec = np.zeros(80, dtype=[("n", "u1"), ("v", ">i4", (3,)), ("part", ">i4")])
    frec["n"], frec["v"] = 3, faces
    path = tmp_path / "be.ply"
    path.write_bytes(header + vrec.tobytes() + frec.tobytes())
    corners, colours, _ = collect(path, 16)
    np.testing.assert_array_equal(corners, verts[faces])
    assert colours is None


def test_raw_soup_round_trip(tmp_path: Path) -> None:
    soup = np.random.default_rng(3).normal(size=(1000, 3, 3)).astype("<f4")
    path = tmp_path / "t.f32"
    path.write_bytes(soup.tobytes())
    corners, _, _ = collect(path, 300)
    np.testing.assert_array_equal(corners, soup.astype(np.float64))


def test_bad_inputs_name_the_file_and_the_problem(tmp_path: Path) -> None:
    odd = tmp_path / "odd.f32"
    odd.write_bytes(b"\0" * 37)
    with pytest.raises(MeshError, match=r"odd\.f32.*multiple of 36"):
        open_triangles(odd)

    stl = tmp_path / "cut.stl"
    write_scene("spheres", 2000, 1, stl)
    stl.write_bytes(stl.read_bytes()[:-10])
    with pytest.raises(MeshError, match=r"cut\.stl: truncated"):
        open_triangles(stl)

    ply = tmp_path / "cut.ply"
    write_scene("spheres", 2000, 1, ply)
    ply.write_bytes(ply.read_bytes()[:-10])
    with pytest.raises(MeshError, match=r"cut\.ply: truncated"):
        open_triangles(ply)

    quads = tmp_path / "quad.ply"
    header = b"ply\nformat binary_little_endian 1.0\nelement vertex 4\nproperty float x\nproperty float y\n"
    header += b"property float z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n"
    square = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], "<f4")
    quads.write_bytes(header + square.tobytes() + bytes([4]) + np.arange(4, dtype="<i4").tobytes())
    corners = np.concatenate([c.corners for c in open_triangles(quads).chunks()])
    np.testing.assert_array_equal(corners, square[[[0, 1, 2], [0, 2, 3]]])  # a fan from the first corner

    nan = tmp_path / "nan.f32"
    soup = np.zeros((5, 3, 3), "<f4")
    soup[3, 1, 2] = np.nan
    nan.write_bytes(soup.tobytes())
    with pytest.raises(MeshError, match="triangle 3 has a non-finite"):
        list(open_triangles(nan).chunks(2))

    nan_ply = tmp_path / "nan.ply"
    nan_ply.write_text(
        "ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\nproperty float z\n"
        "element face 0\nproperty list uchar int vertex_indices\nend_header\n0 0 0\n1 inf 0\n"
    )
    with pytest.raises(MeshError, match=r"nan\.ply: vertex 1 has a non-finite coordinate \(1\.0, inf, 0"):
        open_triangles(nan_ply)

    with pytest.raises(MeshError, match="no such file"):
        open_triangles(tmp_path / "missing.ply")
    with pytest.raises(MeshError, match=r"unsupported file extension '\.xyz'"):
        (tmp_path / "m.xyz").write_text("0 0 0\n")
        open_triangles(tmp_path / "m.xyz")
