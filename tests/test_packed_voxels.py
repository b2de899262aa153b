"""Packed voxels (format version 6, docs/FORMAT.md §10): a six-sample voxel whose faces
show at most two colours takes four words instead of six. Lossless: every face reads the
same sample, so frames are the same, and each such voxel is 8 bytes smaller.

The packed form is checked three ways: against the unpacked build of the same input
(the walker's decoding, tests/modelwalk.py), against the renderer's own decoding
(`native.voxel_face_sample`, what `hit_voxel` calls), and against words this file packs
by the specification from random samples."""

from __future__ import annotations

import functools
import os
import struct
import zlib
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from modelwalk import Node, Walker, WalkError, voxel_samples
from test_build import SMALL_MEMORY, header_offset, rewrite_version

from vastray import native
from vastray.build import BuildOptions, build_model
from vastray.camera import frame_bounds
from vastray.modelfile import HEADER_SIZE, VERSION, ModelError, ModelFile
from vastray.outofcore import OutOfCoreModel, make_cache
from vastray.renderer import Frame

# The real meshes are part of the bar (tests/conftest.py): a missing one fails the build.
MODELS = Path(os.environ.get("VASTRAY_MODELS") or Path(__file__).resolve().parents[2] / "shared" / "models")
SOURCES = {
    "plant": ("scene:plant:60000:3", 2 << 30),  # colours: faces of one voxel differ
    "out-of-core": ("scene:plant:60000:2", SMALL_MEMORY),  # parts emitted in parallel, merged
    "bunny": (str(MODELS / "stanford-bunny.obj"), 2 << 30),  # no colours: every six-sample voxel packs
}
Built = tuple[Path, Path, dict]  # packed, unpacked, the packed build's report


@pytest.fixture(scope="module")
def built(tmp_path_factory: pytest.TempPathFactory) -> Callable[[str], Built]:
    folder = tmp_path_factory.mktemp("packed")

    @functools.cache
    def get(name: str) -> Built:
        source, memory = SOURCES[name]
        packed, unpacked = folder / f"{name}.vast", folder / f"{name}-six.vast"
        # Treelets in version 6's layout (FLAG_PACKED_TREELETS is version 7's, voxel
        # errors version 8's): the files relabelled as version 5 below must hold
        # nothing of a later version.
        options = {"memory": memory, "packed_treelets": False, "voxel_errors": False}
        report = build_model(source, packed, BuildOptions(**options))
        build_model(source, unpacked, BuildOptions(packed_voxels=False, **options))
        return (packed, unpacked, report)

    return get


def lod_nodes(path: Path) -> list[Node]:
    with ModelFile(path) as model:
        return [n for n in Walker(model).walk() if n.kind == "lod"]


def colours(node: Node) -> set[int]:
    return {s & 0x7FFF for s in node.samples}


@pytest.mark.parametrize("name", list(SOURCES))
def test_the_same_samples_in_fewer_bytes(built: Callable[[str], Built], name: str) -> None:
    packed, unpacked, report = built(name)
    a, b = lod_nodes(packed), lod_nodes(unpacked)
    assert len(a) == len(b) > 100
    for x, y in zip(a, b, strict=True):
        assert (x.level, x.lo.tolist(), x.hi.tolist()) == (y.level, y.lo.tolist(), y.hi.tolist())
        assert x.samples == y.samples
        # Packed exactly where six faces show two colours or fewer; one sample stays one.
        six = len(y.samples) == 6
        assert len(y.voxel_words) == len(y.samples)
        assert len(x.voxel_words) == (4 if six and len(colours(y)) <= 2 else len(y.samples))
    count = sum(len(x.voxel_words) == 4 for x in a)
    assert count == report["voxels_packed"] > 0
    if name == "bunny":  # grey everywhere: every six-sample voxel packs
        assert count == report["voxels_six"]
    else:
        assert count < report["voxels_six"]
    with ModelFile(packed) as p, ModelFile(unpacked) as u:
        assert p.header["version"] == u.header["version"] == VERSION == 8

        # A treelet is 8 bytes shorter per packed voxel (its padding to 8 unchanged), so
        # the node levels' raw bytes are too; the triangle level is the same.
        def raw(model: ModelFile, nodes: bool) -> int:
            return sum(
                e.raw_size
                for i, e in enumerate(model.blocks)
                if (model.level_of(i) < model.node_levels) == nodes
            )

        assert raw(u, True) - raw(p, True) == 8 * count
        assert raw(u, False) == raw(p, False)
        assert p.header["file_size"] < u.header["file_size"]


@pytest.mark.parametrize("name", ["plant", "out-of-core"])
def test_the_renderer_reads_the_samples_the_walker_reads(built: Callable[[str], Built], name: str) -> None:
    packed, _, _ = built(name)
    forms = set()
    for node in lod_nodes(packed):
        words = struct.pack(f"<{len(node.voxel_words)}I", *node.voxel_words)
        forms.add(len(node.voxel_words))
        for face in range(6):
            expected = node.samples[0] if len(node.samples) == 1 else node.samples[face]
            assert native.voxel_face_sample(words, face) == expected
    assert forms == {1, 4, 6}


def pack_by_the_specification(six: list[int]) -> list[int]:
    """FORMAT.md §10's packed voxel, written from the text: word 0 holds colour A and
    face 0's normal with bit 30 set; words 1-3, one 96-bit field, hold the normals of
    faces 1-5 at 15 (f - 1), colour B at 75 and at 90 + f a 1 where face f shows B."""
    a = six[0] & 0x7FFF
    b = next((s & 0x7FFF for s in six if s & 0x7FFF != a), a)
    field = b << 75
    for f in range(1, 6):
        field |= ((six[f] >> 15) & 0x7FFF) << (15 * (f - 1))
        field |= (1 if six[f] & 0x7FFF != a else 0) << (90 + f)
    return [
        a | (six[0] & (0x7FFF << 15)) | 1 << 30,
        field & 0xFFFFFFFF,
        (field >> 32) & 0xFFFFFFFF,
        field >> 64,
    ]


def test_every_bit_of_the_packed_form_decodes_as_specified() -> None:
    rng = np.random.default_rng(6)
    for trial in range(2000):
        colour_a, colour_b = (int(c) for c in rng.integers(0, 1 << 15, 2))
        normals = [int(n) for n in rng.integers(0, 1 << 15, 6)]
        shows_b = rng.random(6) < (0.0 if trial % 7 == 0 else 0.5)
        shows_b[0] = False  # colour A is face 0's
        six = [(colour_b if shows_b[f] else colour_a) | normals[f] << 15 for f in range(6)]
        words = pack_by_the_specification(six)
        raw = struct.pack("<4I", *words)
        assert voxel_samples(words) == six  # the walker
        assert [native.voxel_face_sample(raw, f) for f in range(6)] == six  # the renderer
    # A voxel cut short, and a face that does not exist, are errors, not reads past the end.
    with pytest.raises(ValueError, match="cut short"):
        native.voxel_face_sample(struct.pack("<3I", 1 << 30, 0, 0), 0)
    with pytest.raises(ValueError, match="cut short"):
        native.voxel_face_sample(struct.pack("<5I", 0, 0, 0, 0, 0), 2)
    with pytest.raises(ValueError, match="face"):
        native.voxel_face_sample(struct.pack("<I", 1 << 31), 6)


def complete_frames(path: Path, shadings: tuple[str, ...]) -> list[Frame]:
    """A model's complete out-of-core frames of its bounds, at PoE 8, 2 and 0 in each shading."""
    with OutOfCoreModel(path, make_cache(64 << 20, 1)) as model:
        camera = frame_bounds(*model.bounds, width=240, height=160)
        return [
            model.render_complete(camera, pixels_of_error=poe, shading=shading)
            for poe in (8.0, 2.0, 0.0)
            for shading in shadings
        ]


@pytest.mark.parametrize("name", ["plant", "out-of-core"])
def test_frames_are_the_same(built: Callable[[str], Built], name: str) -> None:
    packed, unpacked, _ = built(name)
    shadings = ("headlight", "sun")
    frames = {"packed": complete_frames(packed, shadings), "six": complete_frames(unpacked, shadings)}
    for x, y in zip(frames["packed"], frames["six"], strict=True):
        np.testing.assert_array_equal(x.image, y.image)
        np.testing.assert_array_equal(x.prim, y.prim)
        np.testing.assert_array_equal(x.depth, y.depth)
    assert frames["packed"][0].stats.voxel_hits > 1000  # the far frames draw voxels


def test_the_walker_refuses_a_packed_voxel_in_an_older_version(
    built: Callable[[str], Built], tmp_path: Path
) -> None:
    packed, _, _ = built("bunny")
    copy = tmp_path / "v5.vast"
    copy.write_bytes(packed.read_bytes())
    rewrite_version(copy, 5)
    with ModelFile(copy) as model, pytest.raises(WalkError, match="packed voxel in a version-5 file"):
        for _ in Walker(model).walk():
            pass


def test_a_packed_count_above_the_six_sample_count_is_refused(
    built: Callable[[str], Built], tmp_path: Path
) -> None:
    packed, _, _ = built("bunny")
    with ModelFile(packed) as model:
        six = model.header["voxels_six"]
    data = bytearray(packed.read_bytes())
    struct.pack_into("<Q", data, header_offset("voxels_packed"), six + 1)
    crc_at = header_offset("header_crc32")
    struct.pack_into("<I", data, crc_at, 0)
    struct.pack_into("<I", data, crc_at, zlib.crc32(bytes(data[:HEADER_SIZE])))
    damaged = tmp_path / "damaged.vast"
    damaged.write_bytes(bytes(data))
    with pytest.raises(ModelError, match=f"implausible packed voxel count {six + 1}"):
        ModelFile(damaged)
    # In a version-5 file those bytes were padding: not read.
    rewrite_version(damaged, 5)
    with ModelFile(damaged) as model:
        assert model.header["voxels_packed"] == 0
