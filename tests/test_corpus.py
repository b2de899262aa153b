"""A corpus of every supported input format and variant, written by the tests, each with
the triangles it must read as (an independent reference built in numpy here, not by the
readers): OBJ (polygons, v/vt/vn forms, negative indices, line continuation, o/g/usemtl
parts, vertex and material colours), PLY in ASCII and binary of both byte orders
(triangles, quads and larger polygons as fans, triangle strips with -1 restarts, every
scalar type for coordinates, indices and colours, elements and list properties to skip),
STL binary and ASCII (several solids), OFF and COFF, glTF with an external buffer, with a
data URI and as GLB (several meshes, a node hierarchy with matrix and TRS transforms,
TRIANGLES / TRIANGLE_STRIP / TRIANGLE_FAN, indexed and not, 8/16/32-bit indices,
material and vertex colours), and raw float32 soup.

Every case is read three ways that must agree with the reference: streamed in small
chunks (vastray.triangle_readers), loaded whole (vastray.ingest.load_mesh, whose
triangle ids must name each kept triangle's index in the input), and built
(vastray.build: the report counts the input as the file holds it, then the degenerate
triangles dropped, then what was built; every stored triangle's id names its input
triangle, whose corners the model stores).
"""

from __future__ import annotations

import base64
import json
import struct
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
from modelwalk import walk

from vastray.build import BuildOptions, build_model
from vastray.ingest import load_mesh
from vastray.mesh import MeshError, PartName
from vastray.modelfile import ModelFile
from vastray.triangle_readers import open_triangles

RNG = np.random.default_rng(11)
# Vertices on a grid of quarters, so every format (float, double, ASCII) holds them exactly.
VERTS = RNG.integers(-40, 40, size=(40, 3)) / 4.0


@dataclass
class Case:
    path: Path
    corners: np.ndarray  # (n, 3, 3) float64: the input's triangles in file order
    colours: np.ndarray | None = None  # (n, 3) uint8
    parts: list[PartName] | None = None
    part_ids: np.ndarray | None = None


def fan(polygons: list[list[int]]) -> np.ndarray:
    return np.array([[p[0], p[k], p[k + 1]] for p in polygons for k in range(1, len(p) - 1)], dtype=np.int64)


def strips(rows: list[list[int]]) -> np.ndarray:
    out = []
    for row in rows:
        run: list[int] = []
        for v in row:
            if v < 0:
                run = []
                continue
            run.append(v)
            if len(run) >= 3:
                a, b, c = run[-3:]
                out.append([b, a, c] if (len(run) - 3) % 2 else [a, b, c])
    return np.array(out, dtype=np.int64)


POLYGONS = [[0, 1, 2], [3, 4, 5, 6], [7, 8, 9, 10, 11], [12, 13, 14], [15, 16, 17, 18, 19, 20], [21, 22, 23]]
STRIPS = [[24, 25, 26, 27, 28, -1, 29, 30, 31], [32, 33, 34, 35]]
FACE_RGB = RNG.integers(0, 256, size=(len(POLYGONS), 3)).astype(np.uint8)
VERTEX_RGB = RNG.integers(0, 256, size=(len(VERTS), 3)).astype(np.uint8)


def polygon_colours() -> np.ndarray:
    return np.repeat(FACE_RGB, [len(p) - 2 for p in POLYGONS], axis=0)


def mean_rgb(tris: np.ndarray) -> np.ndarray:
    return np.clip(np.rint(VERTEX_RGB[tris].astype(np.float64).mean(axis=1)), 0, 255).astype(np.uint8)


# ---- writers --------------------------------------------------------------------------------------


def write_obj(path: Path) -> Case:
    mtl = path.with_suffix(".mtl")
    mtl.write_text("newmtl red\nKd 1 0 0\nnewmtl textured\nKd 0 1 0\nmap_Kd wood.png\n")
    lines = ["# a corpus OBJ", f"mtllib {mtl.name}", "o first"]
    lines += [f"v {x} {y} {z}" for x, y, z in VERTS[:12].tolist()]
    lines += ["vt 0 0", "vn 0 0 1", "g one two", "usemtl red"]
    # Triangles, a quad with v/vt/vn, a pentagon with negative (relative) indices.
    lines += ["f 1 2 3", "f 4/1 5/1 6/1 7/1", "f -5//1 -4//1 -3//1 -2//1 \\", "  -1//1"]
    lines += ["o second", "usemtl textured"]
    lines += [f"v {x} {y} {z}" for x, y, z in VERTS[12:21].tolist()]
    lines += ["s off", "f 13/1/1 14/1/1 15/1/1", "l 1 2", "f 16 17 18 19 20 21"]
    path.write_text("\n".join(lines) + "\n")
    polys = [[0, 1, 2], [3, 4, 5, 6], [7, 8, 9, 10, 11], [12, 13, 14], [15, 16, 17, 18, 19, 20]]
    tris = fan(polys)
    # Parts in order of first use: none starts before the first face, "second" with "red".
    parts = [PartName("first", "one two", "red"), PartName("second", "one two", "textured")]
    part_ids = np.array([0] * 6 + [1] * 5, dtype=np.uint32)
    red, white = [255, 0, 0], [255, 255, 255]
    colours = np.array([red] * 6 + [white] * 5, dtype=np.uint8)  # a textured part is not coloured
    return Case(path, VERTS[tris], colours, parts, part_ids)


def write_obj_vertex_colours(path: Path) -> Case:
    lines = [
        f"v {x} {y} {z} {r / 255.0} {g / 255.0} {b / 255.0}"
        for (x, y, z), (r, g, b) in zip(VERTS.tolist(), VERTEX_RGB.tolist(), strict=True)
    ]
    lines += ["f " + " ".join(str(i + 1) for i in p) for p in POLYGONS]
    path.write_text("\n".join(lines) + "\n")
    tris = fan(POLYGONS)
    return Case(path, VERTS[tris], mean_rgb(tris))


PLY_TYPES = {
    "char": "i1",
    "uchar": "u1",
    "short": "i2",
    "ushort": "u2",
    "int": "i4",
    "uint": "u4",
    "float": "f4",
    "double": "f8",
}


def write_ply(
    path: Path,
    fmt: str,
    *,
    coord: str = "float",
    index: str = "int",
    count: str = "uchar",
    face_colour: str | None = "uchar",
    vertex_colour: str | None = None,
    strips_too: bool = True,
) -> Case:
    """Vertices, then an edge element to skip, then polygons (with a list to skip), then
    triangle strips."""
    order = {"binary_little_endian": "<", "binary_big_endian": ">"}.get(fmt, "<")
    head = ["ply", f"format {fmt} 1.0", "comment corpus", f"element vertex {len(VERTS)}"]
    head += [f"property {coord} {a}" for a in "xyz"]
    if vertex_colour:
        head += [f"property {vertex_colour} {c}" for c in ("red", "green", "blue")]
    head += ["property float confidence", "element edge 2", "property int vertex1", "property int vertex2"]
    head += [f"element face {len(POLYGONS)}", f"property list {count} {index} vertex_indices"]
    if face_colour:
        head += [f"property {face_colour} {c}" for c in ("red", "green", "blue")]
    head += ["property list uchar float texcoord"]
    if strips_too:
        head += [f"element tristrips {len(STRIPS)}", f"property list {count} {index} vertex_indices"]
    head.append("end_header")
    scale = (lambda c: c / 255.0) if face_colour in ("float", "double") else (lambda c: c)
    vscale = (lambda c: c / 255.0) if vertex_colour in ("float", "double") else (lambda c: c)

    def num(t: str, v: float) -> str:
        return repr(float(v)) if t in ("float", "double") else str(int(v))

    rows: list[list[tuple[str, float]]] = []
    for i, v in enumerate(VERTS):
        row = [(coord, c) for c in v]
        if vertex_colour:
            row += [(vertex_colour, vscale(c)) for c in VERTEX_RGB[i]]
        rows.append([*row, ("float", 0.5)])
    rows += [[("int", 0), ("int", 1)], [("int", 1), ("int", 2)]]
    for p, rgb in zip(POLYGONS, FACE_RGB, strict=True):
        row = [(count, len(p))] + [(index, i) for i in p]
        if face_colour:
            row += [(face_colour, scale(c)) for c in rgb]
        rows.append([*row, ("uchar", 2), ("float", 0.25), ("float", 0.75)])
    if strips_too:
        # An unsigned index type writes the -1 restart as its largest value.
        restart = -1 if not PLY_TYPES[index].startswith("u") else np.iinfo(PLY_TYPES[index]).max
        rows += [[(count, len(s))] + [(index, i if i >= 0 else restart) for i in s] for s in STRIPS]
    with open(path, "wb") as f:
        f.write(("\n".join(head) + "\n").encode())
        for row in rows:
            if fmt == "ascii":
                f.write((" ".join(num(t, v) for t, v in row) + "\n").encode())
            else:
                f.write(b"".join(np.array([v], dtype=order + PLY_TYPES[t]).tobytes() for t, v in row))
    tris = fan(POLYGONS)
    colours = None
    if vertex_colour:
        colours = mean_rgb(tris)
    if face_colour:
        colours = polygon_colours()
    if strips_too:
        st = strips(STRIPS)
        tris = np.concatenate([tris, st])
        if colours is not None:
            extra = mean_rgb(st) if vertex_colour else np.tile([255, 255, 255], (len(st), 1))
            colours = np.concatenate([colours, extra.astype(np.uint8)])
    return Case(path, VERTS[tris], colours)


def write_stl_binary(path: Path) -> Case:
    tris = fan(POLYGONS)
    rec = np.zeros(len(tris), dtype=[("n", "<f4", (3,)), ("v", "<f4", (3, 3)), ("a", "<u2")])
    rec["v"] = VERTS[tris]
    path.write_bytes(b"binary corpus".ljust(80, b" ") + struct.pack("<I", len(tris)) + rec.tobytes())
    return Case(path, VERTS[tris])


def write_stl_ascii(path: Path) -> Case:
    tris = fan(POLYGONS)
    lines = []
    for name, part in (("bracket", tris[:5]), ("plate", tris[5:])):
        lines.append(f"solid {name}")
        for t in part:
            lines += ["  facet normal 0 0 1", "    outer loop"]
            lines += [f"      vertex {x} {y} {z}" for x, y, z in VERTS[t].tolist()]
            lines += ["    endloop", "  endfacet"]
        lines.append(f"endsolid {name}")
    path.write_text("\n".join(lines) + "\n")
    return Case(
        path,
        VERTS[tris],
        None,
        [PartName("bracket"), PartName("plate")],
        np.array([0] * 5 + [1] * (len(tris) - 5), dtype=np.uint32),
    )


def write_off(path: Path, coloured: bool) -> Case:
    lines = ["COFF" if coloured else "OFF", "# comment", f"{len(VERTS)} {len(POLYGONS)} 0"]
    for i, (x, y, z) in enumerate(VERTS.tolist()):
        extra = " ".join(str(int(c)) for c in VERTEX_RGB[i]) + " 255" if coloured else ""
        lines.append(f"{x} {y} {z} {extra}".strip())
    for k, p in enumerate(POLYGONS):
        colour = " " + " ".join(str(int(c)) for c in FACE_RGB[k]) if k % 2 == 0 else ""
        lines.append(f"{len(p)} " + " ".join(map(str, p)) + colour)
    path.write_text("\n".join(lines) + "\n")
    tris = fan(POLYGONS)
    face = np.repeat(np.arange(len(POLYGONS)), [len(p) - 2 for p in POLYGONS])
    colours = mean_rgb(tris) if coloured else np.tile(np.uint8(255), (len(tris), 3))
    has = face % 2 == 0
    colours[has] = FACE_RGB[face[has]]
    return Case(path, VERTS[tris], colours)


def _gltf(path: Path, kind: str) -> Case:
    """Two meshes placed by a hierarchy: a root with a matrix, a child with TRS placing
    the first mesh, a second node placing it again and one with the second mesh (strip
    and fan primitives, coloured per vertex)."""
    buf = bytearray()

    def view(data: bytes, target: int | None = None) -> int:
        while len(buf) % 4:
            buf.append(0)
        views.append(
            {"buffer": 0, "byteOffset": len(buf), "byteLength": len(data)}
            | ({"target": target} if target else {})
        )
        buf.extend(data)
        return len(views) - 1

    views: list[dict] = []
    accessors: list[dict] = []

    def accessor(array: np.ndarray, component: int, kind_: str) -> int:
        accessors.append(
            {
                "bufferView": view(array.tobytes()),
                "componentType": component,
                "count": len(array),
                "type": kind_,
            }
            | ({"min": array.min(0).tolist(), "max": array.max(0).tolist()} if kind_ == "VEC3" else {})
        )
        return len(accessors) - 1

    pos_a = VERTS[:12].astype("<f4")
    tri_a = fan([[0, 1, 2], [3, 4, 5, 6], [7, 8, 9, 10, 11]])
    pos_b = VERTS[12:24].astype("<f4")
    strip_b = np.arange(6)  # a strip over vertices 0..5
    fan_b = np.arange(6, 12)  # a fan over vertices 6..11
    colours_b = VERTEX_RGB[12:24]
    a_pos = accessor(pos_a, 5126, "VEC3")
    a_idx8 = accessor(tri_a.reshape(-1).astype("u1"), 5121, "SCALAR")
    b_pos = accessor(pos_b, 5126, "VEC3")
    b_col = accessor(colours_b.astype("u1"), 5121, "VEC3")
    accessors[b_col]["normalized"] = True
    b_strip = accessor(strip_b.astype("<u2"), 5123, "SCALAR")
    b_fan = accessor(fan_b.astype("<u4"), 5125, "SCALAR")
    doc = {
        "asset": {"version": "2.0"},
        "scene": 0,
        "scenes": [{"nodes": [0, 3]}],
        "nodes": [
            {"name": "root", "matrix": [2, 0, 0, 0, 0, 2, 0, 0, 0, 0, 2, 0, 1, 2, 3, 1], "children": [1, 2]},
            {
                "name": "a1",
                "mesh": 0,
                "translation": [10, 0, 0],
                "rotation": [0, 0, 0.7071067811865476, 0.7071067811865476],
                "scale": [1, 1, 0.5],
            },
            {"name": "a2", "mesh": 0},
            {"name": "b", "mesh": 1, "translation": [0, -5, 0]},
        ],
        "meshes": [
            {
                "name": "A",
                "primitives": [{"attributes": {"POSITION": a_pos}, "indices": a_idx8, "material": 0}],
            },
            {
                "name": "B",
                "primitives": [
                    {"attributes": {"POSITION": b_pos, "COLOR_0": b_col}, "indices": b_strip, "mode": 5},
                    {"attributes": {"POSITION": b_pos, "COLOR_0": b_col}, "indices": b_fan, "mode": 6},
                    {"attributes": {"POSITION": b_pos}, "mode": 4},
                ],
            },
        ],
        "materials": [{"name": "steel", "pbrMetallicRoughness": {"baseColorFactor": [0.2, 0.4, 0.6, 1.0]}}],
        "accessors": accessors,
        "bufferViews": views,
        "buffers": [{"byteLength": len(buf)}],
    }
    if kind == "gltf-bin":
        doc["buffers"][0]["uri"] = path.stem + ".bin"
        path.with_suffix(".bin").write_bytes(bytes(buf))
        path.write_text(json.dumps(doc))
    elif kind == "gltf-uri":
        doc["buffers"][0]["uri"] = (
            "data:application/octet-stream;base64," + base64.b64encode(bytes(buf)).decode()
        )
        path.write_text(json.dumps(doc))
    else:
        text = json.dumps(doc).encode()
        text += b" " * (-len(text) % 4)
        data = bytes(buf) + b"\0" * (-len(buf) % 4)
        body = (
            struct.pack("<II", len(text), 0x4E4F534A)
            + text
            + struct.pack("<II", len(data), 0x004E4942)
            + data
        )
        path.write_bytes(b"glTF" + struct.pack("<II", 2, 12 + len(body)) + body)

    def placed(m: np.ndarray, p: np.ndarray) -> np.ndarray:
        return p @ m[:3, :3].T + m[:3, 3]

    root = np.array(doc["nodes"][0]["matrix"], dtype=np.float64).reshape(4, 4).T
    c, s = np.cos(np.pi / 2), np.sin(np.pi / 2)
    trs = np.eye(4)
    trs[:3, :3] = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]) * [1, 1, 0.5]
    trs[:3, 3] = [10, 0, 0]
    b_world = np.eye(4)
    b_world[:3, 3] = [0, -5, 0]
    pa, pb = pos_a.astype(np.float64), pos_b.astype(np.float64)
    strip_tris = strips([list(strip_b)])
    fan_tris = np.array([[fan_b[0], fan_b[k], fan_b[k + 1]] for k in range(1, len(fan_b) - 1)])
    plain_tris = np.arange(12).reshape(4, 3)
    corners = np.concatenate(
        [
            placed(root @ trs, pa)[tri_a],
            placed(root, pa)[tri_a],
            placed(b_world, pb)[strip_tris],
            placed(b_world, pb)[fan_tris],
            placed(b_world, pb)[plain_tris],
        ]
    )
    steel = np.rint(np.array([0.2, 0.4, 0.6]) * 255).astype(np.uint8)
    vmean = lambda t: np.rint(colours_b[t].astype(np.float64).mean(axis=1)).astype(np.uint8)  # noqa: E731
    colours = np.concatenate(
        [
            np.tile(steel, (2 * len(tri_a), 1)),
            vmean(strip_tris),
            vmean(fan_tris),
            np.tile(np.uint8(255), (4, 3)),
        ]
    )
    parts = [
        PartName("a1", "A/0", "steel"),
        PartName("a2", "A/0", "steel"),
        PartName("b", "B/0", ""),
        PartName("b", "B/1", ""),
        PartName("b", "B/2", ""),
    ]
    part_ids = np.repeat(np.arange(5), [len(tri_a), len(tri_a), len(strip_tris), len(fan_tris), 4]).astype(
        np.uint32
    )
    return Case(path, corners, colours, parts, part_ids)


def write_soup(path: Path) -> Case:
    tris = fan(POLYGONS)
    VERTS[tris].astype("<f4").tofile(path)
    return Case(path, VERTS[tris])


CORPUS: dict[str, Callable[[Path], Case]] = {
    "obj": lambda d: write_obj(d / "parts.obj"),
    "obj-vertex-colours": lambda d: write_obj_vertex_colours(d / "vc.obj"),
    "ply-ascii": lambda d: write_ply(d / "a.ply", "ascii"),
    "ply-ascii-double-vertex-colours": lambda d: write_ply(
        d / "ad.ply", "ascii", coord="double", face_colour=None, vertex_colour="uchar"
    ),
    "ply-le": lambda d: write_ply(d / "le.ply", "binary_little_endian"),
    "ply-be": lambda d: write_ply(
        d / "be.ply", "binary_big_endian", coord="double", index="uint", count="ushort"
    ),
    "ply-le-short-indices-float-colours": lambda d: write_ply(
        d / "ls.ply", "binary_little_endian", index="ushort", count="uint", face_colour="float"
    ),
    "ply-be-char-indices-vertex-colours": lambda d: write_ply(
        d / "bc.ply", "binary_big_endian", index="uchar", face_colour=None, vertex_colour="float"
    ),
    "ply-le-polygons-only": lambda d: write_ply(d / "lp.ply", "binary_little_endian", strips_too=False),
    "stl-binary": lambda d: write_stl_binary(d / "b.stl"),
    "stl-ascii": lambda d: write_stl_ascii(d / "a.stl"),
    "off": lambda d: write_off(d / "m.off", False),
    "coff": lambda d: write_off(d / "c.off", True),
    "gltf-bin": lambda d: _gltf(d / "scene.gltf", "gltf-bin"),
    "gltf-uri": lambda d: _gltf(d / "inline.gltf", "gltf-uri"),
    "glb": lambda d: _gltf(d / "scene.glb", "glb"),
    "soup": lambda d: write_soup(d / "s.f32"),
}
EXPECTED_TRIANGLES = {  # counted by hand: a polygon of n corners is n - 2 triangles, a strip run of n too
    "obj": 11,
    "obj-vertex-colours": 12,
    "ply-ascii": 18,
    "ply-ascii-double-vertex-colours": 18,
    "ply-le": 18,
    "ply-be": 18,
    "ply-le-short-indices-float-colours": 18,
    "ply-be-char-indices-vertex-colours": 18,
    "ply-le-polygons-only": 12,
    "stl-binary": 12,
    "stl-ascii": 12,
    "off": 12,
    "coff": 12,
    "gltf-bin": 24,
    "gltf-uri": 24,
    "glb": 24,
    "soup": 12,
}


@pytest.fixture(params=sorted(CORPUS))
def case(request: pytest.FixtureRequest, tmp_path: Path) -> tuple[str, Case]:
    return request.param, CORPUS[request.param](tmp_path)


def test_the_reference_counts(case: tuple[str, Case]) -> None:
    name, c = case
    assert len(c.corners) == EXPECTED_TRIANGLES[name]


def test_streamed_in_small_chunks(case: tuple[str, Case]) -> None:
    _, c = case
    source = open_triangles(c.path)
    chunks = list(source.chunks(4))
    assert all(ch.count <= 4 for ch in chunks)
    corners = np.concatenate([ch.corners for ch in chunks])
    np.testing.assert_allclose(corners, c.corners, rtol=0, atol=1e-12)
    assert np.concatenate([ch.triangle_ids for ch in chunks]).tolist() == list(range(len(c.corners)))
    assert source.triangle_count == len(c.corners) and source.exact_count
    assert source.has_colours == (c.colours is not None)
    if c.colours is not None:
        np.testing.assert_array_equal(np.concatenate([ch.colours for ch in chunks]), c.colours)


def test_loaded_whole(case: tuple[str, Case]) -> None:
    _, c = case
    mesh = load_mesh(c.path)
    np.testing.assert_allclose(mesh.vertices[mesh.faces.astype(np.int64)], c.corners, rtol=0, atol=1e-12)
    assert mesh.triangle_ids.tolist() == list(range(len(c.corners)))
    assert mesh.input_triangles == len(c.corners)
    if c.colours is None:
        assert mesh.face_colours is None
    else:
        np.testing.assert_array_equal(mesh.face_colours, c.colours)
    assert mesh.parts == c.parts
    if c.parts is not None:
        np.testing.assert_array_equal(mesh.part_ids, c.part_ids)


def test_built(case: tuple[str, Case], tmp_path: Path) -> None:
    _, c = case
    out = tmp_path / "m.vast"
    report = build_model(c.path, out, BuildOptions(memory=64 << 20))
    assert report["input_triangles"] == len(c.corners)
    assert report["degenerate"] + report["triangles"] == report["input_triangles"]
    stored = stored_triangles(out)
    centre = np.array(ModelFile(out).header["centre"])
    expected = (c.corners - centre).astype(np.float32)
    for tid, corners in stored.items():
        np.testing.assert_array_equal(corners, expected[tid])


def stored_triangles(path: Path) -> dict[int, np.ndarray]:
    """{input id: its float32 corners} of every triangle a built model stores."""
    out: dict[int, np.ndarray] = {}
    with ModelFile(path) as model:
        for node in walk(model):
            if node.kind == "leaf":
                assert node.ids is not None and node.vertices is not None
                for tid, v in zip(node.ids.tolist(), node.vertices, strict=True):
                    out[tid] = v
    return out


# ---- triangle ids whatever was dropped --------------------------------------------------------------

# A strip of quads (2 triangles each) with a degenerate triangle after every third: repeated
# corners, collinear corners and a point, so the kept ones are numbered around the gaps.
GOOD = np.array([[[i, 0, 0], [i + 1, 0, 0], [i, 1, 0]] for i in range(0, 60, 2)], dtype=np.float64)


def with_degenerates() -> tuple[np.ndarray, list[int]]:
    tris, bad = [], []
    for i, t in enumerate(GOOD):
        tris.append(t)
        if i % 3 == 2:
            bad.append(len(tris))
            kind = len(bad) % 3
            tris.append(
                [t[0], t[0], t[1]]
                if kind == 0
                else [t[0], (t[0] + t[1]) / 2, t[1]]
                if kind == 1
                else [t[2]] * 3
            )
    return np.array(tris), bad


def write_as(fmt: str, path: Path, tris: np.ndarray) -> None:
    n = len(tris)
    if fmt == "obj":
        lines = [f"v {x} {y} {z}" for x, y, z in tris.reshape(-1, 3).tolist()]
        lines += [f"f {3 * i + 1} {3 * i + 2} {3 * i + 3}" for i in range(n)]
        path.write_text("\n".join(lines) + "\n")
    elif fmt == "ply":
        header = (
            f"ply\nformat binary_little_endian 1.0\nelement vertex {3 * n}\nproperty double x\n"
            f"property double y\nproperty double z\nelement face {n}\n"
            "property list uchar int vertex_indices\nend_header\n"
        )
        faces = np.zeros(n, dtype=[("n", "u1"), ("v", "<i4", (3,))])
        faces["n"], faces["v"] = 3, np.arange(3 * n).reshape(n, 3)
        path.write_bytes(header.encode() + tris.astype("<f8").tobytes() + faces.tobytes())
    elif fmt == "stl":
        rec = np.zeros(n, dtype=[("n", "<f4", (3,)), ("v", "<f4", (3, 3)), ("a", "<u2")])
        rec["v"] = tris
        path.write_bytes(b"\0" * 80 + struct.pack("<I", n) + rec.tobytes())
    else:  # glb, one non-indexed primitive
        pos = tris.reshape(-1, 3).astype("<f4").tobytes()
        doc = {
            "asset": {"version": "2.0"},
            "scenes": [{"nodes": [0]}],
            "nodes": [{"mesh": 0}],
            "meshes": [{"primitives": [{"attributes": {"POSITION": 0}}]}],
            "accessors": [{"bufferView": 0, "componentType": 5126, "count": 3 * n, "type": "VEC3"}],
            "bufferViews": [{"buffer": 0, "byteLength": len(pos)}],
            "buffers": [{"byteLength": len(pos)}],
        }
        text = json.dumps(doc).encode()
        text += b" " * (-len(text) % 4)
        body = (
            struct.pack("<II", len(text), 0x4E4F534A) + text + struct.pack("<II", len(pos), 0x004E4942) + pos
        )
        path.write_bytes(b"glTF" + struct.pack("<II", 2, 12 + len(body)) + body)


@pytest.mark.parametrize("fmt", ["obj", "ply", "stl", "glb"])
def test_triangle_ids_name_the_inputs_own_triangles(fmt: str, tmp_path: Path) -> None:
    """Degenerate triangles interleaved: the loaded mesh's ids, the built model's stored
    ids and the ids a full-detail pick of the built model returns all name the input's
    own triangle (its index in the file)."""
    tris, bad = with_degenerates()
    path = tmp_path / f"d.{fmt}"
    write_as(fmt, path, tris)
    kept = np.array([i for i in range(len(tris)) if i not in bad])

    with pytest.warns(UserWarning, match=f"dropped {len(bad)} degenerate"):
        mesh = load_mesh(path)
    assert mesh.triangle_ids.tolist() == kept.tolist() and mesh.input_triangles == len(tris)
    np.testing.assert_array_equal(mesh.vertices[mesh.faces.astype(np.int64)], tris[kept])

    out = tmp_path / "d.vast"
    report = build_model(path, out)
    assert (report["input_triangles"], report["degenerate"], report["triangles"]) == (
        len(tris),
        len(bad),
        len(kept),
    )
    stored = stored_triangles(out)
    assert sorted(stored) == kept.tolist()
    centre = np.array(ModelFile(out).header["centre"])
    for tid, corners in stored.items():
        np.testing.assert_array_equal(corners, (tris[tid] - centre).astype(np.float32))

    # Picks: a ray down onto each kept triangle's centroid hits that triangle's id.
    with ModelFile(out) as model:
        scene = model.to_scene()
    centroids = tris[kept].mean(axis=1)
    origins = centroids + np.array([0.0, 0.0, 1.0])
    hits = scene.intersect(origins, np.tile([0.0, 0.0, -1.0], (len(kept), 1)))
    assert hits["prim"].tolist() == kept.tolist()


# ---- bad input ----------------------------------------------------------------------------------

ASCII_TRIANGLE = (
    "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\n"
    "element face 1\nproperty list uchar int vertex_indices\nend_header\n0 0 0\n1 0 0\n0 1 0\n"
)


@pytest.mark.parametrize(
    ("name", "content", "message"),
    [
        ("zero.obj", "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 0 1 2\n", r"line 4: vertex index 0"),
        ("two.obj", "v 0 0 0\nv 1 0 0\nf 1 2\n", r"line 3: a face needs at least three vertices"),
        (
            "far.obj",
            "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 9\n",
            r"face 0 refers to vertex 8, but there are only 3 vertices",
        ),
        (
            "rel.obj",
            "v 0 0 0\nf -1 -2 -3\n",
            r"line 2: relative vertex index -2 reaches before the first vertex",
        ),
        ("word.obj", "v 0 0 zero\n", r"line 1: a vertex needs three coordinates"),
        (
            "line.ply",
            ASCII_TRIANGLE + "2 0 1\n",
            r"a face with 2 vertices",
        ),
        (
            "cut.ply",
            ASCII_TRIANGLE + "3 0 1\n",
            r"face 0: the file ends inside this row",
        ),
        (
            "cut.stl",
            "solid x\n facet normal 0 0 1\n  outer loop\n   vertex 0 0 0\n   vertex 1 0 0\n",
            r"the file ends inside a facet",
        ),
        ("bad.off", "OFF\n3 1 0\n0 0 0\n1 0 0\n0 1 0\n3 0 1\n", r"face 0: a face lists fewer vertices"),
        (
            "draco.gltf",
            json.dumps({"asset": {"version": "2.0"}, "extensionsRequired": ["KHR_draco_mesh_compression"]}),
            r"extensions KHR_draco_mesh_compression are not supported",
        ),
        (
            "nobuf.gltf",
            json.dumps({"asset": {"version": "2.0"}, "buffers": [{"uri": "missing.bin", "byteLength": 4}]}),
            r"buffer 0: .*missing.bin not found",
        ),
    ],
)
def test_bad_files_name_the_file_and_the_problem(
    tmp_path: Path, name: str, content: str, message: str
) -> None:
    path = tmp_path / name
    path.write_text(content)
    with pytest.raises(MeshError, match=message) as err:
        load_mesh(path)
    assert str(path) in str(err.value)
    out = tmp_path / "m.vast"
    with pytest.raises(MeshError, match=message):
        build_model(path, out)
    assert sorted(p.name for p in tmp_path.iterdir()) == [name]  # the build left nothing behind
