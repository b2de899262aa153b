"""Parts stored in the model (docs/FORMAT.md §4a, docs/ingest.md "Colours and parts"):
the part table and the runs of part over input triangle ids, built from OBJ, glTF and
PLY inputs and checked against independent computations from the input text; a model
without parts has no section; damage and old versions are reported clearly."""

from __future__ import annotations

import base64
import json
import struct
import zlib
from pathlib import Path

import numpy as np
import pytest
from modelwalk import read_parts

from vastray import cli
from vastray.build import BuildOptions, build_model
from vastray.ingest import load_mesh
from vastray.modelfile import FLAG_PART_IDS, HEADER_SIZE, NO_PART, VERSION, ModelError, ModelFile, ModelPart
from vastray.outofcore import OutOfCoreModel, make_cache

# ---- helpers --------------------------------------------------------------------------------


def fix_header_crc(data: bytearray) -> None:
    struct.pack_into("<I", data, 196, 0)
    struct.pack_into("<I", data, 196, zlib.crc32(bytes(data[:HEADER_SIZE])))


def set_version(path: Path, version: int) -> None:
    data = bytearray(path.read_bytes())
    struct.pack_into("<I", data, 8, version)
    fix_header_crc(data)
    path.write_bytes(bytes(data))


def rewrite_section(path: Path, edit) -> None:  # type: ignore[no-untyped-def]
    """Edits the parts section and fixes its checksum and the header's, so only the
    structure the edit broke is wrong."""
    data = bytearray(path.read_bytes())
    offset, size = struct.unpack_from("<QQ", data, 200)
    section = bytearray(data[offset : offset + size])
    edit(section)
    data[offset : offset + size] = section
    struct.pack_into("<I", data, 216, zlib.crc32(bytes(section)))
    fix_header_crc(data)
    path.write_bytes(bytes(data))


def expected_from_obj(text: str) -> dict:
    """An independent reading of an OBJ (v, f, o, g, usemtl only): per input triangle
    its corners (float64) and display name, in file order (fans), and which are kept (no
    repeated corner). Bounds as stored: centre + float32(v - centre), in double."""
    verts: list[list[float]] = []
    obj = group = mtl = ""
    tris: list[tuple[int, int, int]] = []
    names: list[str] = []
    for line in text.splitlines():
        w = line.split()
        if not w:
            continue
        if w[0] == "v":
            verts.append([float(x) for x in w[1:4]])
        elif w[0] == "o":
            obj = " ".join(w[1:])
        elif w[0] == "g":
            group = " ".join(w[1:])
        elif w[0] == "usemtl":
            mtl = " ".join(w[1:])
        elif w[0] == "f":
            idx = [int(x.split("/")[0]) - 1 for x in w[1:]]
            for k in range(1, len(idx) - 1):
                tris.append((idx[0], idx[k], idx[k + 1]))
                names.append(" / ".join(n for n in (obj, group, mtl) if n) or "(unnamed)")
    v = np.array(verts, dtype=np.float64)
    t = np.array(tris, dtype=np.int64)
    centre = 0.5 * (v.min(axis=0) + v.max(axis=0))
    local = (v - centre).astype(np.float32).astype(np.float64)
    kept = (t[:, 0] != t[:, 1]) & (t[:, 1] != t[:, 2]) & (t[:, 0] != t[:, 2])
    order: list[str] = []  # parts with kept triangles, in order of first use
    for name, keep in zip(names, kept, strict=True):
        if keep and name not in order:
            order.append(name)
    table = {}
    for name in order:
        sel = np.array([n == name for n in names]) & kept
        corners = local[t[sel]].reshape(-1, 3)
        table[name] = (centre + corners.min(axis=0), centre + corners.max(axis=0), int(sel.sum()),
                       v[t[sel]].reshape(-1, 3).min(axis=0))  # fmt: skip
    part_of = np.array([order.index(n) if n in table else -1 for n in names], dtype=np.int32)
    return {"order": order, "table": table, "part_of": part_of, "count": len(t), "kept": int(kept.sum())}


def parts_obj(triangles: int, seed: int = 7) -> str:
    """An OBJ of about `triangles` random triangles, in parts: faces before any o, then
    objects and groups (one coming back later, so runs outnumber parts), a material, a
    quad, degenerate faces, and a group whose only faces are degenerate."""
    rng = np.random.default_rng(seed)
    n_v = max(16, triangles // 2)
    v = 1000.0 + rng.random((n_v, 3)) * np.array([10.0, 3.0, 7.0])
    lines = [f"v {float(x)!r} {float(y)!r} {float(z)!r}" for x, y, z in v]

    def faces(k: int, degenerate: int = 0) -> list[str]:
        idx = rng.integers(1, n_v + 1, size=(k, 3))
        out = [f"f {a} {b} {c}" for a, b, c in idx if len({a, b, c}) == 3]
        for a in rng.integers(1, n_v + 1, size=degenerate):
            out.append(f"f {a} {a} {a % n_v + 1}")
        return out

    share = max(1, triangles // 6)
    lines += faces(share, 2)
    lines += ["o alpha", *faces(share, 1)]
    lines += ["g g1", *faces(share), "f 1 2 3 4"]
    lines += ["o beta", *faces(share, 3)]
    lines += ["g dead", *faces(0, 4)]  # a part of degenerate faces only: not stored
    lines += ["o alpha", "g g1", *faces(share)]  # alpha / g1 again
    lines += ["o gamma", "usemtl steel", *faces(triangles - 5 * share)]
    return "\n".join(lines) + "\n"


def check_against(model: ModelFile, exp: dict) -> None:
    parts = model.parts
    assert [p.name for p in parts] == exp["order"]
    assert [p.id for p in parts] == list(range(len(parts)))
    for p in parts:
        lo, hi, count, plain_lo = exp["table"][p.name]
        assert p.triangles == count
        assert p.lo == tuple(lo) and p.hi == tuple(hi)  # exactly the stored triangles' bounds
        np.testing.assert_allclose(p.lo, plain_lo, rtol=1e-6)  # and the input's, to f32 rounding
        assert isinstance(p, ModelPart)
    assert sum(p.triangles for p in parts) <= model.header["triangle_count"] == exp["kept"]
    ids = np.arange(exp["count"])
    np.testing.assert_array_equal(model.part_of(ids), exp["part_of"])
    assert model.part_of(np.array([-1, exp["count"], exp["count"] + 5])).tolist() == [-1, -1, -1]
    firsts, run_parts = model.part_runs
    assert firsts.dtype == np.uint32 and run_parts.dtype == np.int32
    assert firsts[0] == 0 and (np.diff(firsts.astype(np.int64)) > 0).all()
    assert (run_parts[1:] != run_parts[:-1]).all()  # neighbouring runs of equal part are merged
    # An independent read of the bytes agrees.
    section = read_parts(model.path)
    assert section is not None
    assert section.names == exp["order"]
    np.testing.assert_array_equal(section.run_firsts, firsts)
    stored = section.run_parts.astype(np.int64)
    np.testing.assert_array_equal(np.where(stored == NO_PART, -1, stored), run_parts)
    assert model.header["flags"] & FLAG_PART_IDS and model.header["version"] == VERSION >= 2


# ---- OBJ ------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def obj_parts(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict]:
    folder = tmp_path_factory.mktemp("parts")
    text = parts_obj(30_000)
    (folder / "parts.obj").write_text(text)
    return folder / "parts.obj", expected_from_obj(text)


def test_obj_parts_are_stored_with_names_counts_bounds_and_runs(obj_parts, tmp_path: Path) -> None:
    source, exp = obj_parts
    assert {"(unnamed)", "alpha / g1", "gamma / g1 / steel"} <= set(exp["order"])
    assert not any("dead" in name for name in exp["order"])  # only degenerate faces: dropped
    report = build_model(source, tmp_path / "m.vast")
    assert report["parts"] == len(exp["order"]) and report["incore_parts"] == 1
    with ModelFile(tmp_path / "m.vast") as model:
        check_against(model, exp)
        firsts, _ = model.part_runs
        assert len(firsts) > len(model.parts)  # alpha / g1 comes back
        model.to_scene()  # the blocks are unaffected


def test_out_of_core_build_stores_the_same_parts(obj_parts, tmp_path: Path) -> None:
    source, exp = obj_parts
    report = build_model(source, tmp_path / "ooc.vast", BuildOptions(memory=3 << 20))
    assert report["incore_parts"] > 1 and report["out_of_core_levels"] >= 1
    build_model(source, tmp_path / "in.vast")
    with ModelFile(tmp_path / "ooc.vast") as ooc, ModelFile(tmp_path / "in.vast") as incore:
        check_against(ooc, exp)
        assert ooc.parts == incore.parts
        for a, b in zip(ooc.part_runs, incore.part_runs, strict=True):
            np.testing.assert_array_equal(a, b)


def test_out_of_core_model_and_inspect_show_the_parts(obj_parts, tmp_path: Path, capsys) -> None:
    source, exp = obj_parts
    build_model(source, tmp_path / "m.vast")
    with OutOfCoreModel(tmp_path / "m.vast", make_cache(1 << 20, 1)) as model:
        assert [p.name for p in model.parts] == exp["order"]
        np.testing.assert_array_equal(model.part_of(np.arange(exp["count"])), exp["part_of"])
    assert cli.main(["inspect", "--json", str(tmp_path / "m.vast")]) == 0
    stats = json.loads(capsys.readouterr().out)
    assert [p["name"] for p in stats["parts"]] == exp["order"]
    assert set(stats["parts"][0]) == {"id", "name", "lo", "hi", "triangles"}
    assert cli.main(["inspect", str(tmp_path / "m.vast")]) == 0
    assert f"parts      {len(exp['order'])}" in capsys.readouterr().out


# ---- glTF and PLY ---------------------------------------------------------------------------


def test_gltf_nodes_are_parts(tmp_path: Path) -> None:
    quad = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], dtype="<f4")
    index = np.array([0, 1, 2, 0, 2, 3], dtype="<u2")
    blob = quad.tobytes() + index.tobytes()
    doc = {
        "asset": {"version": "2.0"},
        "buffers": [{"byteLength": len(blob), "uri": "data:;base64," + base64.b64encode(blob).decode()}],
        "bufferViews": [{"buffer": 0, "byteOffset": 0, "byteLength": 48},
                        {"buffer": 0, "byteOffset": 48, "byteLength": 12}],
        "accessors": [{"bufferView": 0, "componentType": 5126, "count": 4, "type": "VEC3",
                       "min": [0, 0, 0], "max": [1, 1, 0]},
                      {"bufferView": 1, "componentType": 5123, "count": 6, "type": "SCALAR"}],
        "meshes": [{"name": "square", "primitives": [{"attributes": {"POSITION": 0}, "indices": 1}]}],
        "nodes": [{"name": "left", "mesh": 0, "translation": [-2, 0, 0]},
                  {"name": "right", "mesh": 0, "translation": [3, 0, 1]}],
        "scenes": [{"nodes": [0, 1]}],
    }  # fmt: skip
    (tmp_path / "two.gltf").write_text(json.dumps(doc))
    assert build_model(tmp_path / "two.gltf", tmp_path / "two.vast")["parts"] == 2
    with ModelFile(tmp_path / "two.vast") as model:
        assert model.parts == [
            ModelPart(0, "left / square/0", (-2.0, 0.0, 0.0), (-1.0, 1.0, 0.0), 2),
            ModelPart(1, "right / square/0", (3.0, 0.0, 1.0), (4.0, 1.0, 1.0), 2),
        ]
        assert model.part_of(np.arange(4)).tolist() == [0, 0, 1, 1]
        assert model.part_runs[0].tolist() == [0, 2]


def write_ply(path: Path, fmt: str, faces: list[list[int]], parts: list[int], prop: str = "part") -> None:
    verts = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0, 0, 1], [5, 0, 2]], dtype=np.float64)
    head = (f"ply\nformat {fmt} 1.0\nelement vertex {len(verts)}\nproperty float x\nproperty float y\n"
            f"property float z\nelement face {len(faces)}\nproperty list uchar int vertex_indices\n"
            f"property int {prop}\nend_header\n")  # fmt: skip
    if fmt == "ascii":
        body = "".join(f"{x:g} {y:g} {z:g}\n" for x, y, z in verts)
        body += "".join(f"{len(f)} {' '.join(map(str, f))} {p}\n" for f, p in zip(faces, parts, strict=True))
        path.write_bytes(head.encode() + body.encode())
        return
    data = verts.astype("<f4").tobytes()
    for f, p in zip(faces, parts, strict=True):
        data += struct.pack(f"<B{len(f)}ii", len(f), *f, p)
    path.write_bytes(head.encode() + data)


TRI_FACES = [[0, 1, 2], [0, 2, 3], [0, 1, 4], [1, 2, 4], [2, 3, 4], [3, 0, 4], [1, 5, 2]]
TRI_PARTS = [5, 5, 9, 5, 9, 9, 2]  # interleaved: five runs over three parts


@pytest.mark.parametrize(
    ("fmt", "faces", "parts", "part_of"),
    [
        ("ascii", TRI_FACES, TRI_PARTS, [0, 0, 1, 0, 1, 1, 2]),
        ("binary_little_endian", TRI_FACES, TRI_PARTS, [0, 0, 1, 0, 1, 1, 2]),
        # A quad: binary faces parsed row by row; both its triangles are in its part.
        ("binary_little_endian", [[0, 1, 2, 3], *TRI_FACES[2:]], [7, *TRI_PARTS[2:]], [0, 0, 1, 2, 1, 1, 3]),
    ],
    ids=["ascii", "binary", "binary-polygons"],
)
def test_ply_part_property(tmp_path: Path, fmt: str, faces, parts, part_of) -> None:  # type: ignore[no-untyped-def]
    write_ply(tmp_path / "p.ply", fmt, faces, parts)
    report = build_model(tmp_path / "p.ply", tmp_path / "p.vast")
    names = [f"part {v}" for v in dict.fromkeys(parts)]
    assert report["parts"] == len(names)
    with ModelFile(tmp_path / "p.vast") as model:
        assert [p.name for p in model.parts] == names
        assert model.part_of(np.arange(len(part_of))).tolist() == part_of
        firsts, _run_parts = model.part_runs
        assert len(firsts) > len(names)
        verts = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0, 0, 1], [5, 0, 2]], float)
        tris = [t for f in faces for t in ([f[0], f[k], f[k + 1]] for k in range(1, len(f) - 1))]
        for p in model.parts:
            mine = np.array([t for t, q in zip(tris, part_of, strict=True) if q == p.id])
            assert p.triangles == len(mine)
            assert p.lo == tuple(verts[mine].reshape(-1, 3).min(axis=0))
            assert p.hi == tuple(verts[mine].reshape(-1, 3).max(axis=0))
    mesh = load_mesh(tmp_path / "p.ply")
    assert mesh.parts is not None and [p.object for p in mesh.parts] == names
    np.testing.assert_array_equal(mesh.part_ids, part_of)


def test_a_float_ply_property_named_part_is_not_a_part(tmp_path: Path) -> None:
    path = tmp_path / "f.ply"
    write_ply(path, "ascii", TRI_FACES, TRI_PARTS)
    path.write_bytes(path.read_bytes().replace(b"property int part", b"property float part"))
    assert build_model(path, tmp_path / "f.vast")["parts"] == 0


# ---- no parts, damage, versions ---------------------------------------------------------------


@pytest.fixture
def plain(tmp_path: Path) -> Path:
    """A model whose input has no parts (an OBJ without o, g or usemtl), untiered and with
    nothing that came after version 1 (no flag, no packed voxels): the layout of version 1
    (it passes for a version-1 file below; a tiered file is version 5's alone,
    tests/test_tiers.py)."""
    text = "\n".join(line for line in parts_obj(600).splitlines() if line.split()[0] in ("v", "f"))
    (tmp_path / "plain.obj").write_text(text + "\n")
    options = BuildOptions(tier_width=0, quantized_splits=False, packed_voxels=False)
    assert build_model(tmp_path / "plain.obj", tmp_path / "plain.vast", options)["parts"] == 0
    return tmp_path / "plain.vast"


@pytest.fixture
def with_parts(tmp_path: Path) -> Path:
    """Untiered and without quantized splits, so that relabelled as version 1 only its
    parts flag is unknown."""
    (tmp_path / "some.obj").write_text(parts_obj(600))
    options = BuildOptions(tier_width=0, quantized_splits=False, packed_voxels=False)
    build_model(tmp_path / "some.obj", tmp_path / "some.vast", options)
    return tmp_path / "some.vast"


def test_an_input_without_parts_stores_no_section(plain: Path) -> None:
    with ModelFile(plain) as model:
        h = model.header
        assert model.parts == [] and model.part_of(np.arange(5)).tolist() == [-1] * 5
        assert not h["flags"] & FLAG_PART_IDS
        assert (h["parts_offset"], h["parts_size"], h["parts_crc32"], h["part_count"]) == (0, 0, 0, 0)
        # The version-1 layout: the blocks run to the end of the file.
        assert h["file_size"] == h["data_offset"] + sum(e.stored_size for e in model.blocks)
        assert model.stats()["parts"] == []
    assert plain.read_bytes()[200:HEADER_SIZE] == bytes(HEADER_SIZE - 200)
    assert read_parts(plain) is None


def test_a_version_1_file_still_opens(plain: Path, with_parts: Path) -> None:
    with ModelFile(plain) as model:
        triangles = model.to_scene().triangle_count
    set_version(plain, 1)  # a version-1 file is this one with its version field
    with ModelFile(plain) as model:
        assert model.header["version"] == 1 and model.parts == []
        assert model.to_scene().triangle_count == triangles
    with OutOfCoreModel(plain, make_cache(1 << 20, 1)) as model:
        assert model.parts == []
    set_version(with_parts, 1)  # version 1 has no part-ids flag
    with pytest.raises(ModelError, match="unsupported attribute flags 0x6"):
        ModelFile(with_parts)
    with pytest.raises(ModelError, match="unsupported attribute flags"):
        OutOfCoreModel(with_parts, make_cache(1 << 20, 1))


def test_an_unknown_version_says_rebuild(with_parts: Path) -> None:
    set_version(with_parts, VERSION + 1)
    message = (
        rf"format version {VERSION + 1} is not supported \(this vastray reads versions 1 to {VERSION}\); rebu"
    )
    with pytest.raises(ModelError, match=message):
        ModelFile(with_parts)
    with pytest.raises(ModelError, match=message):
        OutOfCoreModel(with_parts, make_cache(1 << 20, 1))


def test_a_flipped_byte_in_the_parts_section_is_reported(with_parts: Path) -> None:
    data = bytearray(with_parts.read_bytes())
    offset, size = struct.unpack_from("<QQ", data, 200)
    for at in (offset + 1, offset + size // 2, offset + size - 1):  # counts, records or runs, names
        damaged = bytearray(data)
        damaged[at] ^= 0x10
        with_parts.write_bytes(bytes(damaged))
        with pytest.raises(ModelError, match="parts section damaged"):
            ModelFile(with_parts)
        with pytest.raises(ModelError, match="parts section damaged"):
            OutOfCoreModel(with_parts, make_cache(1 << 20, 1))


def test_broken_part_structure_is_refused(with_parts: Path) -> None:
    original = with_parts.read_bytes()
    with ModelFile(with_parts) as model:
        parts = len(model.parts)
        runs = len(model.part_runs[0])
    runs_at = 8 + 64 * parts

    def swap_runs(s: bytearray) -> None:
        a, b = s[runs_at : runs_at + 8], s[runs_at + 8 : runs_at + 16]
        s[runs_at : runs_at + 16] = b + a

    def bad_part(s: bytearray) -> None:
        struct.pack_into("<I", s, runs_at + 4, parts)

    def bad_name(s: bytearray) -> None:
        struct.pack_into("<I", s, 8 + 56, len(s))

    assert runs >= 2
    for edit, message in ((swap_runs, "part runs are out of order"),
                          (bad_part, "a part run names a part outside the part table"),
                          (bad_name, "part 0: its name lies outside the names blob")):  # fmt: skip
        with_parts.write_bytes(original)
        rewrite_section(with_parts, edit)
        with pytest.raises(ModelError, match=message):
            ModelFile(with_parts)
    # An unknown flag bit is refused.
    data = bytearray(original)
    struct.pack_into("<I", data, 16, struct.unpack_from("<I", data, 16)[0] | 1 << 9)
    fix_header_crc(data)
    with_parts.write_bytes(bytes(data))
    with pytest.raises(ModelError, match="unsupported attribute flags"):
        ModelFile(with_parts)
    # Bytes appended after the section are caught by the file size, cut ones too.
    with_parts.write_bytes(original[:-1])
    with pytest.raises(ModelError, match="truncated or appended to"):
        ModelFile(with_parts)
