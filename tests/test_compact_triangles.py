"""Compact triangle blocks (FLAG_COMPACT_TRIANGLES, format version 5, FORMAT.md §11a): a
build option that stores each leaf's list as a bit-packed record, the triangles in groups
of 8 with corner, id and palette fields as narrow as the group needs, and the vertices
bit-packed without rounding to bytes. It is lossless, so the tests build the same input
with plain and with compact blocks and check that the decoded scenes and every frame
agree bit for bit (in core and out of core; with shadow and ambient-occlusion rays, which
skip their own triangle by id), that the walker of tests/modelwalk.py (FORMAT.md alone)
decodes what the native reader decodes, that a leaf too big for one block continues into
the next, that the file does not depend on the thread count in or out of core, and that
damaged blocks are reported by the decoder and the walker and drawn by the traversal
without reading past the block."""

from __future__ import annotations

import os
import struct
import zlib
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from modelwalk import COMPACT_HEADER, GROUP, TIERED, BitReader, Walker, WalkError, walk
from test_build import SMALL_MEMORY, rewrite_version, run_cli
from test_model_writer import fan, write_ply
from views import model_views

from vastray import native
from vastray.build import BuildOptions, build_model
from vastray.camera import frame_bounds
from vastray.modelfile import (
    FLAG_COMPACT_TRIANGLES,
    FLAG_QUANTIZED_SPLITS,
    VERSION,
    ModelError,
    ModelFile,
)
from vastray.outofcore import OutOfCoreModel, make_cache
from vastray.renderer import PRIM_VOXEL, trace

# The real meshes are part of the bar (tests/conftest.py): a missing one fails the build.
MODELS = Path(os.environ.get("VASTRAY_MODELS") or Path(__file__).resolve().parents[2] / "shared" / "models")
SOURCES = {
    "plant": ("scene:plant:60000:3", 2 << 30),  # colours and parts
    "out-of-core": ("scene:plant:60000:2", SMALL_MEMORY),
    "bunny": (str(MODELS / "stanford-bunny.obj"), 2 << 30),  # a scan; quantized: 59-bit vertex records
}
# "full": full precision, untiered, six-word voxels: a layout version 4 had; "both": both reduced-
# precision options, tiered (the default).
KINDS = {"full": {"quantized_splits": False, "tier_width": 0, "packed_voxels": False},
         "both": {"quantized_splits": True, "quantized_vertices": True}}  # fmt: skip
Key = tuple[str, str, bool]  # source, kind, compact


@pytest.fixture(scope="module")
def models(tmp_path_factory: pytest.TempPathFactory) -> dict[Key, Path]:
    folder = tmp_path_factory.mktemp("compact")
    out = {}
    for name, (source, memory) in SOURCES.items():
        for kind, options in KINDS.items():
            for compact in (False, True):
                path = folder / f"{name}-{kind}-{'c' if compact else 'p'}.vast"
                build_model(source, path, BuildOptions(memory=memory, compact_triangles=compact, **options))
                out[name, kind, compact] = path
    return out


def assert_same_frame(a, b) -> None:  # type: ignore[no-untyped-def]
    np.testing.assert_array_equal(a.prim, b.prim)
    np.testing.assert_array_equal(a.depth, b.depth)
    np.testing.assert_array_equal(a.image, b.image)


def test_the_header_says_which_and_the_file_is_smaller(models: dict[Key, Path]) -> None:
    for (name, kind, compact), path in models.items():
        with ModelFile(path) as model:
            assert model.header["version"] == VERSION == 8
            assert bool(model.header["flags"] & FLAG_COMPACT_TRIANGLES) == compact
            assert model.compact_triangles == compact == model.stats()["compact_triangles"]
            if compact:
                with ModelFile(models[name, kind, False]) as plain:
                    assert model.header["file_size"] < 0.85 * plain.header["file_size"], name
                    # The same tree: only the triangle level differs.
                    assert model.levels[:-1] == plain.levels[:-1]
                    assert model.header["references"] == plain.header["references"]
    assert native.FORMAT["flag_compact_triangles"] == 1 << 5


@pytest.mark.parametrize("name", SOURCES)
def test_same_scene_and_frames(models: dict[Key, Path], name: str) -> None:
    """Plain and compact decode to the same scene and give the same frames, in core and
    out of core, at full detail (headlight, sun with shadow rays, ambient occlusion) and
    at a pixel of error; out of core equals in core on the decoded compact model."""
    for kind in KINDS:
        plain, compact = models[name, kind, False], models[name, kind, True]
        with ModelFile(plain) as p, ModelFile(compact) as c:
            scene_p, scene_c = p.to_scene(), c.to_scene()
        np.testing.assert_array_equal(scene_p.local_vertices, scene_c.local_vertices)
        cache = make_cache(256 << 20, 1)
        with OutOfCoreModel(plain, cache) as ooc_p, OutOfCoreModel(compact, cache) as ooc_c:
            for camera in model_views(plain):
                in_core = trace(scene_c, camera)
                assert_same_frame(trace(scene_p, camera), in_core)
                assert (in_core.prim >= 0).mean() > 0.05
                frame = ooc_c.render_complete(camera, pixels_of_error=0.0)
                assert frame.complete
                assert_same_frame(frame, in_core)
                for shading in ("sun", "ao"):
                    fields = {"shading": shading, "ao_samples": 4, "pixels_of_error": 0.0}
                    assert_same_frame(
                        ooc_p.render_complete(camera, **fields), ooc_c.render_complete(camera, **fields)
                    )
                assert_same_frame(
                    ooc_p.render_complete(camera, pixels_of_error=2.0),
                    ooc_c.render_complete(camera, pixels_of_error=2.0),
                )


@pytest.mark.parametrize("name", ["plant", "bunny"])
def test_walks_in_flight_read_compact_leaves_alike(
    models: dict[Key, Path], name: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Packets in flight (on large models, forced here with VASTRAY_INTERLEAVE_BYTES=0)
    stop before each of a compact leaf's record, group headers, corner fields and
    vertices, decoding what has arrived to ask for the next: every packet size, and single
    rays, give the plain model's frame, at full detail and with voxels."""
    monkeypatch.setenv("VASTRAY_INTERLEAVE_BYTES", "0")
    for kind in KINDS:
        cache = make_cache(256 << 20, 1)
        with OutOfCoreModel(models[name, kind, False], cache) as plain, \
                OutOfCoreModel(models[name, kind, True], cache) as compact:  # fmt: skip
            seen = 0.0
            for camera in model_views(models[name, kind, False]):
                for poe in (0.0, 2.0):
                    expected = plain.render_complete(camera, pixels_of_error=poe, packets=1)
                    seen = max(seen, float((expected.prim >= 0).mean()))
                    for packets in (1, 4, 16):
                        frame = compact.render_complete(camera, pixels_of_error=poe, packets=packets)
                        assert_same_frame(frame, expected)
            assert seen > 0.05


def leaves(path: Path) -> list:
    with ModelFile(path) as model:
        return [node for node in walk(model) if node.kind == "leaf"]


@pytest.mark.parametrize("name", SOURCES)
def test_walker_and_native_decode_the_same(models: dict[Key, Path], name: str) -> None:
    """The walker reads the compact blocks on its own: every leaf lists the same triangles
    in the same order as the plain build's, with the same vertices and colours, and the
    native decoder agrees with it."""
    split, total = split_groups(models[name, "both", True])
    assert 0 < split < total  # both ways of storing a group's ids are read
    for kind in KINDS:
        plain, compact = leaves(models[name, kind, False]), leaves(models[name, kind, True])
        assert len(plain) == len(compact)
        with ModelFile(models[name, kind, True]) as model:
            corners = model.to_scene().local_vertices
        for a, b in zip(plain, compact, strict=True):
            np.testing.assert_array_equal(a.ids, b.ids)
            np.testing.assert_array_equal(a.vertices, b.vertices)
            if a.colours is None:
                assert b.colours is None
            else:
                np.testing.assert_array_equal(a.colours, b.colours)
            np.testing.assert_array_equal(corners[b.ids.astype(np.int64)], b.vertices)


def split_groups(path: Path) -> tuple[int, int]:
    """(groups whose ids use two bases, all groups) over the compact triangle blocks."""
    split = total = 0
    with ModelFile(path) as model:
        first, count = model.levels[-1]
        for b in range(first, first + count):
            raw = model.read_block(b)
            layout = model.triangle_layout(raw)
            before = 16 + (layout["vertices_count"] - 1).bit_length() + 5 + layout["id_bits"] + 6
            for j in range(layout["group_count"]):
                split += BitReader(raw, 8 * layout["groups"] + j * layout["header_bits"] + before)(1)
            total += layout["group_count"]
    return split, total


def record_starts(path: Path) -> list[tuple[int, int, int]]:
    """(partial, entries, bytes of the block) of the first leaf record of each compact
    triangle block."""
    out = []
    with ModelFile(path) as model:
        first, count = model.levels[-1]
        for b in range(first, first + count):
            raw = model.read_block(b)
            r = BitReader(raw, 8 * COMPACT_HEADER + 21)
            partial = r(1)
            out.append((partial, r(16) if partial else 0, len(raw)))
    return out


@pytest.mark.slow
def test_a_leaf_bigger_than_a_block_continues(tmp_path: Path) -> None:
    """A fan of 20,000 triangles around one vertex: the leaf at its centre holds more
    triangles than a compact block takes, so its record says it is partial and the leaf
    goes on in the next blocks; every triangle decodes to its input, out of core too."""
    n = 20_000
    corners, colours = fan(n)
    write_ply(tmp_path / "fan.ply", corners, colours)
    path = tmp_path / "fan.vast"
    build_model(tmp_path / "fan.ply", path, BuildOptions(compact_triangles=True))
    starts = record_starts(path)
    continued = [entries for partial, entries, _ in starts if partial]
    assert continued, f"no leaf continues: {starts}"
    walked = leaves(path)  # the walker is slow on this deep tree: one walk serves both checks
    big = max(walked, key=lambda node: len(node.ids))
    assert len(big.ids) > max(continued)
    assert sorted({int(i) for node in walked for i in node.ids}) == list(range(n))
    with ModelFile(path) as model:
        scene = model.to_scene()
    origins = np.column_stack([corners.mean(axis=1)[:, 0], np.full(n, 1.0), corners.mean(axis=1)[:, 2]])
    hits = scene.intersect(origins, np.tile([0.0, -1.0, 0.0], (n, 1)))
    assert (hits["prim"] == np.arange(n)).mean() > 0.999
    with ModelFile(path) as model:
        camera = frame_bounds(*model.bounds, width=128, height=96, direction=(0.2, 1.0, 0.3))
    with OutOfCoreModel(path, make_cache(64 << 20, 1)) as ooc:
        assert_same_frame(ooc.render_complete(camera, pixels_of_error=0.0), trace(scene, camera))


@pytest.mark.parametrize("memory", [2 << 30, SMALL_MEMORY], ids=["in-core", "out-of-core"])
def test_output_does_not_depend_on_the_thread_count(tmp_path: Path, memory: int) -> None:
    """1, 2 and 3 threads write the same bytes, built in core (a part big enough for
    parallel emission, whose triangle blocks are merged) and out of core."""
    files = []
    for threads in (1, 2, 3):
        path = tmp_path / f"t{threads}.vast"
        options = BuildOptions(
            threads=threads, memory=memory, compact_triangles=True, quantized_vertices=True
        )
        report = build_model("scene:plant:200000:3", path, options)
        assert report["references"] >= 1 << 19
        assert (report["incore_parts"] > 1) == (memory == SMALL_MEMORY)
        files.append(path.read_bytes())
    assert files[0] == files[1] == files[2]


def test_old_versions_and_the_flag(tmp_path: Path, models: dict[Key, Path]) -> None:
    """A file without the flag (or packed voxels) reads as version 4 (the plain layout is version
    4's); a compact file cannot pass for version 4 (the flag came with version 5)."""
    plain, compact = models["plant", "full", False], models["plant", "full", True]
    camera = model_views(plain)[0]
    with ModelFile(plain) as model:
        reference = trace(model.to_scene(), camera)
    copy = tmp_path / "v4.vast"
    copy.write_bytes(plain.read_bytes())
    rewrite_version(copy, 4)
    with OutOfCoreModel(copy, make_cache(64 << 20, 1)) as ooc:
        assert_same_frame(ooc.render_complete(camera, pixels_of_error=0.0), reference)
    copy.write_bytes(compact.read_bytes())
    rewrite_version(copy, 4)
    with pytest.raises(ModelError, match="unsupported attribute flags"):
        ModelFile(copy)
    with pytest.raises(ModelError, match="unsupported attribute flags"):
        OutOfCoreModel(copy, make_cache(1 << 20, 1))


def test_cli(tmp_path: Path) -> None:
    """`vastray build` writes quantized splits unless told not to, compact blocks when
    asked, and `inspect` says so."""
    flags = {}
    for name, extra in (
        ("default", []),
        ("compact", ["--compact-triangles"]),
        ("full", ["--no-quantized-splits"]),
    ):
        out = tmp_path / f"{name}.vast"
        result = run_cli("build", "scene:plant:3000:1", "-o", str(out), *extra, cwd=tmp_path)
        assert result.returncode == 0, result.stderr
        flags[name] = struct.unpack_from("<I", out.read_bytes(), 16)[0]
    assert flags["default"] & FLAG_QUANTIZED_SPLITS and not flags["default"] & FLAG_COMPACT_TRIANGLES
    assert flags["compact"] & FLAG_COMPACT_TRIANGLES
    assert not flags["full"] & FLAG_QUANTIZED_SPLITS
    result = run_cli("inspect", str(tmp_path / "compact.vast"), cwd=tmp_path)
    assert "compact triangles" in result.stdout, result.stdout


# ---- damaged blocks ------------------------------------------------------------------------------


def replace_block(src: Path, dst: Path, block: int, raw: bytes) -> None:
    """`dst`: `src` with block `block` replaced by `raw`, stored uncompressed under a
    checksum of its own, so that it passes every container check (FORMAT.md §3-5) and
    only its contents are wrong; the index, header and parts offset follow."""
    data = src.read_bytes()
    level_count = struct.unpack_from("<I", data, 28)[0]
    flags, tier_count = struct.unpack_from("<I", data, 16)[0], struct.unpack_from("<I", data, 224)[0]
    records = level_count * (tier_count if flags & TIERED else 1)  # a tiered table: a record per stream
    block_count, index_offset, data_offset, raw_bytes = struct.unpack_from("<4Q", data, 152)
    parts_offset, parts_size = struct.unpack_from("<QQ", data, 200)
    at = index_offset + 24 * records
    entries = [list(struct.unpack_from("<QIIII", data, at + 24 * i)) for i in range(block_count)]
    blocks = [data[e[0] : e[0] + e[1]] for e in entries]
    raw_bytes += len(raw) - entries[block][2]
    blocks[block] = raw
    entries[block][1:] = [len(raw), len(raw), zlib.crc32(raw), 0]
    out = bytearray(data[:data_offset])
    offset = data_offset
    for i, e in enumerate(entries):
        e[0] = offset
        offset += e[1]
        struct.pack_into("<QIIII", out, at + 24 * i, *e)
    section = data[parts_offset : parts_offset + parts_size]
    struct.pack_into("<2Q", out, 176, raw_bytes, offset + len(section))
    if parts_size:
        struct.pack_into("<Q", out, 200, offset)
    struct.pack_into("<I", out, 192, zlib.crc32(bytes(out[index_offset:data_offset])))
    struct.pack_into("<I", out, 196, 0)
    struct.pack_into("<I", out, 196, zlib.crc32(bytes(out[:256])))
    dst.write_bytes(bytes(out) + b"".join(blocks) + section)


def put_bits(raw: bytearray, pos: int, width: int, value: int) -> None:
    for i in range(width):
        byte, bit = divmod(pos + i, 8)
        raw[byte] = (raw[byte] & ~(1 << bit)) | (((value >> i) & 1) << bit)


class Fields:
    """Where the fields of a compact block lie (FORMAT.md §11a), for damaging them."""

    def __init__(self, raw: bytes, has_colours: bool) -> None:
        _, verts, _, palette, _, id_bits, groups, _ = struct.unpack_from("<8I", raw)
        self.vertex_bits = (verts - 1).bit_length()
        self.palette_bits = (palette - 1).bit_length() if has_colours else 0
        self.group = 8 * groups  # group 0's header
        self.offset = self.group  # its data offset, 16 bits
        self.corner_base = self.group + 16
        self.corner_width = self.corner_base + self.vertex_bits
        self.palette_base = self.corner_width + 5 + id_bits + 7  # past the id width and split bit
        self.record = 8 * COMPACT_HEADER  # the first leaf record: base (16), width (5), partial (1)


def damaged_blocks(raw: bytes, has_colours: bool) -> list[tuple[str, bytes, str, str]]:
    """(what, damaged raw block, the native decoder's message, the walker's) for one
    compact block."""
    f = Fields(raw, has_colours)
    ones = (1 << f.vertex_bits) - 1

    def word(at: int, value: int) -> Callable[[bytearray], None]:
        return lambda d: struct.pack_into("<I", d, at, value)

    def field(pos: int, width: int, value: int) -> Callable[[bytearray], None]:
        return lambda d: put_bits(d, pos, width, value)

    def count(d: bytearray) -> None:  # the record says it is partial, with more entries than its leaf
        put_bits(d, f.record + 21, 1, 1)
        put_bits(d, f.record + 22, 16, 0xFFFF)

    cases = [
        ("no triangles", "header is damaged", "counts are damaged", word(0, 0)),
        ("palette past the block", "header is damaged", "section offsets", word(28, len(raw) + 64)),
        ("a byte appended", "does not match its section counts", "section offsets", lambda d: d.append(0)),
        ("corner width 31", "triangle group is damaged", "field widths", field(f.corner_width, 5, 31)),
        ("group data past the data", "triangle group is damaged", "past the group data",
         field(f.offset, 16, 0xFFFF)),
        ("corners past the vertices", "past the vertex section", "past the vertex section",
         field(f.corner_base, f.vertex_bits, ones)),
        ("record base past the triangles", "entry points past the triangle section", "past the triangles",
         field(f.record, 16, 0xFFFF)),
        ("record count past the leaf", "bad count", "count", count),
    ]  # fmt: skip
    if has_colours:
        cases.append(("colour past the palette", "colour points past the palette", "past the palette",
                      field(f.palette_base, f.palette_bits, (1 << f.palette_bits) - 1)))  # fmt: skip
    out = []
    for what, native_says, walker_says, change in cases:
        data = bytearray(raw)
        change(data)
        out.append((what, bytes(data), native_says, walker_says))
    return out


def test_damaged_blocks_are_reported_and_read_safely(
    models: dict[Key, Path], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Bad counts, widths and offsets in a compact block (under a valid checksum): the
    native decoder names the block and what is wrong, the walker refuses it, and the
    out-of-core traversal draws the view without reading outside the block (a record or
    group it cannot trust ends the leaf as if the block were missing)."""
    # Untiered: a tiered file stores many triangles in blocks of two tiers, and the decoder
    # reads a triangle where it meets it first, which need not be the damaged block.
    source = models["plant", "full", True]
    with ModelFile(source) as model:
        block = model.levels[-1][0]  # the first triangle block: every field of it is in use
        raw = model.read_block(block)
        assert model.has_colours
        good = trace(model.to_scene(), model_views(source)[0])
        input_triangles = model.header["input_triangles"]
    assert Fields(raw, True).palette_bits > 0
    cases = damaged_blocks(raw, True)
    assert len(cases) == 9
    for what, data, native_says, walker_says in cases:
        path = tmp_path / "damaged.vast"
        replace_block(source, path, block, data)
        with ModelFile(path) as model:
            assert model.read_block(block) == data
            with pytest.raises(ModelError, match=f"model block {block}: .*{native_says}"):
                model.to_scene()
            with pytest.raises(WalkError, match=walker_says):
                list(Walker(model).walk())
        # Packets one at a time, and (forced) in flight, whose leaf waits decode the block too.
        for interleave_from, packets in (("", 16), ("0", 16), ("0", 1)):
            monkeypatch.setenv("VASTRAY_INTERLEAVE_BYTES", interleave_from)
            with OutOfCoreModel(path, make_cache(64 << 20, 1)) as ooc:
                frame = ooc.render_complete(
                    model_views(source)[0], pixels_of_error=0.0, packets=packets, timeout=60
                )
            hits = frame.prim >= 0
            assert (frame.prim[hits] < input_triangles).all(), what
            assert hits.sum() + (frame.prim == PRIM_VOXEL).sum() > 0.5 * (good.prim >= 0).sum(), what
    assert GROUP == 8
