"""Mesh ingest: real models, bad input, degenerate triangles, colours."""

from __future__ import annotations

import os
import re
import warnings
from pathlib import Path

import numpy as np
import pytest
import trimesh

from vastray.ingest import load_mesh
from vastray.mesh import DegenerateTrianglesWarning, Mesh, MeshError, validate

REPO = Path(__file__).resolve().parents[1]
MODELS = Path(os.environ.get("VASTRAY_MODELS", REPO.parent / "shared" / "models"))


def _readme_counts() -> dict[str, tuple[int, int]]:
    """{file: (triangles, vertices in the file)} from the models folder's README table."""
    readme = MODELS / "README.md"
    if not readme.is_file():
        pytest.fail(f"models folder not found at {MODELS}; set VASTRAY_MODELS")
    counts = {}
    for line in readme.read_text().splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if len(cells) >= 3 and cells[0].endswith(".obj"):
            tris = int(cells[1].replace(",", ""))
            verts = int(re.match(r"[\d,]+", cells[2]).group(0).replace(",", ""))
            counts[cells[0]] = (tris, verts)
    return counts


def _obj_faces(path: Path) -> np.ndarray:
    faces = []
    with open(path) as fh:
        for line in fh:
            if line.startswith("f "):
                faces.append([int(tok.split("/")[0]) - 1 for tok in line.split()[1:]])
    return np.array(faces)


def test_readme_lists_every_model() -> None:
    listed = set(_readme_counts())
    present = {p.name for p in MODELS.glob("*.obj")}
    assert listed and listed == present


@pytest.mark.parametrize("name", sorted(p.name for p in MODELS.glob("*.obj")))
def test_real_models_load_with_readme_counts(name: str) -> None:
    tris, verts = _readme_counts()[name]
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # none of these has degenerate triangles
        mesh = load_mesh(MODELS / name)
    assert mesh.triangle_count == tris
    # Vertices are neither merged, split at texture seams, nor pruned.
    assert mesh.vertices.shape == (verts, 3)
    assert mesh.vertices.dtype == np.float64 and mesh.faces.dtype == np.uint32
    assert mesh.face_colours is None
    lo, hi = mesh.bounds()
    assert np.all(lo < hi)


def test_triangle_ids_follow_file_order() -> None:
    for name in ("teapot.obj", "spot.obj"):
        mesh = load_mesh(MODELS / name)
        assert np.array_equal(mesh.faces, _obj_faces(MODELS / name))


def _write(path: Path, text: str) -> Path:
    path.write_text(text)
    return path


NAN_OBJ = "v 0 0 0\nv 1 0 0\nv 0 1 0\nv {bad} 0 1\nv 1 1 1\nf 1 2 3\nf 1 2 4\nf 2 3 5\n"
BAD_PLY = """ply
format ascii 1.0
element vertex 4
property float x
property float y
property float z
element face 2
property list uchar int vertex_indices
end_header
0 0 0
1 0 0
0 1 {bad}
0 0 1
3 0 1 2
3 0 1 3
"""


@pytest.mark.parametrize(
    ("suffix", "template", "index"),
    [(".obj", NAN_OBJ, 3), (".ply", BAD_PLY, 2)],
)
@pytest.mark.parametrize("bad", ["nan", "inf", "-inf"])
def test_non_finite_vertex_is_rejected(
    tmp_path: Path, suffix: str, template: str, index: int, bad: str
) -> None:
    path = _write(tmp_path / f"broken{suffix}", template.format(bad=bad))
    with pytest.raises(MeshError) as err:
        load_mesh(path)
    message = str(err.value)
    assert str(path) in message
    assert f"vertex {index} " in message
    assert bad.lstrip("-") in message.lower()


def test_bad_vertex_index_counts_unused_vertices(tmp_path: Path) -> None:
    # Vertex 0 is used by no face; the message must still count it, as the file does.
    text = "v 9 9 9\nv 0 0 0\nv 1 0 0\nv 0 nan 0\nf 2 3 4\n"
    with pytest.raises(MeshError, match=r"vertex 3 "):
        load_mesh(_write(tmp_path / "unused.obj", text))


@pytest.mark.parametrize(
    ("name", "text"),
    [
        ("comments.obj", "# nothing here\n"),
        ("points.obj", "v 0 0 0\nv 1 0 0\nv 0 1 0\n"),
        ("noface.ply", BAD_PLY.replace("element face 2", "element face 0").format(bad=0)[:-20]),
    ],
)
def test_empty_mesh_is_rejected(tmp_path: Path, name: str, text: str) -> None:
    path = _write(tmp_path / name, text)
    with pytest.raises(MeshError, match="empty") as err:
        load_mesh(path)
    assert str(path) in str(err.value)


def test_missing_unknown_and_garbage_files(tmp_path: Path) -> None:
    missing = tmp_path / "nope.obj"
    with pytest.raises(MeshError, match="no such file") as err:
        load_mesh(missing)
    assert str(missing) in str(err.value)

    unknown = _write(tmp_path / "mesh.xyz", "0 0 0\n")
    with pytest.raises(MeshError, match="unsupported file extension") as err:
        load_mesh(unknown)
    assert str(unknown) in str(err.value)

    garbage = tmp_path / "garbage.ply"
    garbage.write_bytes(b"\x00\x01\x02 not a ply at all")
    with pytest.raises(MeshError, match="cannot parse") as err:
        load_mesh(garbage)
    assert str(garbage) in str(err.value)


def _ply_with_face_colours(path: Path, vertices, faces, colours) -> Path:
    mesh = trimesh.Trimesh(vertices, faces, process=False)
    rgba = np.concatenate([colours, np.full((len(colours), 1), 255)], axis=1).astype(np.uint8)
    mesh.visual.face_colors = rgba
    path.write_bytes(mesh.export(file_type="ply"))
    return path


def test_degenerate_triangles_dropped_and_colours_stay_aligned(tmp_path: Path) -> None:
    vertices = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [2, 0, 0], [0, 0, 1]], dtype=np.float64)
    faces = np.array(
        [
            [0, 1, 2],  # fine
            [0, 1, 1],  # repeated index
            [0, 1, 3],  # three distinct but collinear vertices
            [0, 2, 4],  # fine
            [4, 4, 4],  # a point
        ]
    )
    colours = np.array([[10, 0, 0], [20, 0, 0], [30, 0, 0], [40, 0, 0], [50, 0, 0]])
    path = _ply_with_face_colours(tmp_path / "degenerate.ply", vertices, faces, colours)
    with pytest.warns(DegenerateTrianglesWarning) as record:
        mesh = load_mesh(path)
    assert len(record) == 1
    assert str(record[0].message) == f"{path}: dropped 3 degenerate triangles"
    assert mesh.faces.tolist() == [[0, 1, 2], [0, 2, 4]]
    assert mesh.face_colours.tolist() == [[10, 0, 0], [40, 0, 0]]


def test_tiny_but_valid_triangles_are_kept() -> None:
    # fandisk-like coordinates: small, but the area is not zero in float64.
    v = np.array([[0, 0, 0], [1e-6, 0, 0], [0, 1e-6, 0]], dtype=np.float64)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        out = validate(Mesh(v, np.array([[0, 1, 2]], np.uint32), None, "t"), "tiny")
    assert out.triangle_count == 1


def test_validate_rejects_bad_indices_and_all_degenerate() -> None:
    v = np.zeros((3, 3))
    v[1, 0] = v[2, 1] = 1.0
    with pytest.raises(MeshError, match=r"src: face 1 refers to vertex 3"):
        validate(Mesh(v, np.array([[0, 1, 2], [0, 1, 3]]), None, "m"), "src")
    with pytest.raises(MeshError, match="src: all 1 triangles are degenerate"):
        validate(Mesh(v, np.array([[0, 0, 1]]), None, "m"), "src")
    with pytest.raises(MeshError, match="face_colours"):
        validate(Mesh(v, np.array([[0, 1, 2]]), np.zeros((2, 3), np.uint8), "m"), "src")


def test_face_colours_round_trip_and_absent_colours(tmp_path: Path) -> None:
    box = trimesh.creation.box()
    rng = np.random.default_rng(3)
    colours = rng.integers(0, 256, (len(box.faces), 3))
    coloured = _ply_with_face_colours(tmp_path / "coloured.ply", box.vertices, box.faces, colours)
    mesh = load_mesh(coloured)
    assert mesh.face_colours is not None and mesh.face_colours.dtype == np.uint8
    assert np.array_equal(mesh.face_colours, colours)

    plain = tmp_path / "plain.ply"
    plain.write_bytes(trimesh.creation.box().export(file_type="ply"))
    assert load_mesh(plain).face_colours is None
    # Even a file whose colours equal trimesh's grey default keeps them: they are real.
    grey = np.tile([102, 102, 102], (len(box.faces), 1))
    path = _ply_with_face_colours(tmp_path / "grey.ply", box.vertices, box.faces, grey)
    assert np.array_equal(load_mesh(path).face_colours, grey)


def test_vertex_colours_are_averaged_per_face(tmp_path: Path) -> None:
    mesh = trimesh.Trimesh([[0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 1, 2]], process=False)
    mesh.visual.vertex_colors = [[255, 0, 0, 255], [0, 255, 0, 255], [0, 0, 30, 255]]
    path = tmp_path / "vc.ply"
    path.write_bytes(mesh.export(file_type="ply"))
    assert load_mesh(path).face_colours.tolist() == [[85, 85, 10]]


@pytest.mark.parametrize("file_type", ["stl", "off", "glb", "obj"])
def test_other_formats(tmp_path: Path, file_type: str) -> None:
    box = trimesh.creation.box(extents=(1.0, 2.0, 3.0))
    path = tmp_path / f"box.{file_type}"
    data = box.export(file_type=file_type)
    path.write_bytes(data if isinstance(data, bytes) else data.encode())
    mesh = load_mesh(path)
    assert mesh.triangle_count == 12
    lo, hi = mesh.bounds()
    assert np.allclose(hi - lo, [1.0, 2.0, 3.0])


def test_scene_parts_are_placed_and_coloured(tmp_path: Path) -> None:
    red = trimesh.creation.box()
    red.visual = trimesh.visual.TextureVisuals(
        material=trimesh.visual.material.PBRMaterial(baseColorFactor=[255, 0, 0, 255])
    )
    plain = trimesh.creation.box()
    scene = trimesh.Scene()
    scene.add_geometry(red, node_name="red")
    scene.add_geometry(
        plain, node_name="moved", transform=trimesh.transformations.translation_matrix([10, 0, 0])
    )
    path = tmp_path / "two.glb"
    path.write_bytes(scene.export(file_type="glb"))
    mesh = load_mesh(path)
    assert mesh.triangle_count == 24
    lo, hi = mesh.bounds()
    assert np.allclose(lo, [-0.5, -0.5, -0.5]) and np.allclose(hi, [10.5, 0.5, 0.5])
    # The part without material gets glTF's default white.
    assert sorted({tuple(c) for c in mesh.face_colours.tolist()}) == [(255, 0, 0), (255, 255, 255)]


def test_obj_material_colours(tmp_path: Path) -> None:
    (tmp_path / "m.mtl").write_text("newmtl red\nKd 1 0 0\nnewmtl blue\nKd 0 0 1\n")
    text = "mtllib m.mtl\nv 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nusemtl red\nf 1 2 3\nusemtl blue\nf 1 2 4\n"
    mesh = load_mesh(_write(tmp_path / "m.obj", text))
    assert sorted(mesh.face_colours.tolist()) == [[0, 0, 255], [255, 0, 0]]


def test_bounds_ignore_unused_vertices() -> None:
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [100, 100, 100]], dtype=np.float64)
    lo, hi = Mesh(v, np.array([[0, 1, 2]], np.uint32), None, "m").bounds()
    assert lo.tolist() == [0, 0, 0] and hi.tolist() == [1, 1, 0]
