"""The write phase (vastray/model_assembly.py): a large build's blocks stay where the
native writer appended them in the model file, behind room for the header and the index
that the last blocks written fill; a small one, or one whose index would not fit that
room, is written whole, every block in id order.

Either way the model is the same: the same header fields, index entries and block bytes
for every block id, only the blocks' offsets differ; and every reader takes both (the
Python reader, the native block cache, the independent walker's layout checks).
"""

from __future__ import annotations

import os
import struct
import subprocess
import sys
import zlib
from pathlib import Path

import numpy as np
import pytest
from modelwalk import TIER_COUNT_AT, read_parts
from views import model_views, render_camera

from vastray import model_assembly, native
from vastray.build import BuildOptions, build_model
from vastray.modelfile import HEADER_SIZE, ModelFile
from vastray.outofcore import make_cache
from vastray.renderer import Frame

# The real meshes are part of the bar (tests/conftest.py): a missing one fails the build.
MODELS = Path(os.environ.get("VASTRAY_MODELS") or Path(__file__).resolve().parents[2] / "shared" / "models")
SOURCE = "scene:plant:120000:3"


def in_id_order(data: bytes) -> bytes:
    """The model `data` with its blocks rewritten one after the other in id order from
    the end of the index (the parts section after them), offsets, sizes and checksums
    updated: pure Python, from the file's bytes and FORMAT.md §3-5 alone."""
    level_count, flags = struct.unpack_from("<I", data, 28)[0], struct.unpack_from("<I", data, 16)[0]
    tiers = struct.unpack_from("<I", data, TIER_COUNT_AT)[0] if flags & (1 << 6) else 1
    block_count, index_offset, data_offset = struct.unpack_from("<3Q", data, 152)
    parts_offset, parts_size = struct.unpack_from("<QQ", data, 200)
    at = index_offset + 24 * level_count * tiers
    out = bytearray(data[:data_offset])
    blocks = []
    offset = data_offset
    for i in range(block_count):
        old, stored = struct.unpack_from("<QI", data, at + 24 * i)
        blocks.append(data[old : old + stored])
        struct.pack_into("<Q", out, at + 24 * i, offset)
        offset += stored
    section = data[parts_offset : parts_offset + parts_size]
    struct.pack_into("<Q", out, 184, offset + len(section))
    if parts_size:
        struct.pack_into("<Q", out, 200, offset)
    struct.pack_into("<I", out, 192, zlib.crc32(bytes(out[index_offset:data_offset])))
    struct.pack_into("<I", out, 196, 0)
    struct.pack_into("<I", out, 196, zlib.crc32(bytes(out[:HEADER_SIZE])))
    return bytes(out) + b"".join(blocks) + section


def frames(path: Path) -> list[Frame]:
    """Complete full-detail frames of two views, through the native block cache."""
    cache = make_cache(256 << 20)
    model = cache.open(str(path))
    out = []
    for camera in model_views(path):
        for _ in range(200):
            frame = render_camera(model, camera, pixels_of_error=0.0)
            if frame.complete:
                break
            cache.drain()
        assert frame.complete and (frame.prim >= 0).any()
        out.append(frame)
    model.close()
    return out


@pytest.fixture(scope="module")
def built(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict]:
    out = tmp_path_factory.mktemp("assembly") / "in_place.vast"
    return out, build_model(SOURCE, out, BuildOptions(memory=64 << 20))


def test_a_large_build_keeps_its_blocks_where_they_were_written(built: tuple[Path, dict]) -> None:
    path, report = built
    assert report["blocks_in_place"]
    front = model_assembly.front_reserve(report["triangles"])
    with ModelFile(path) as model:
        model.verify()
        h = model.header
        offsets = np.array([b.offset for b in model.blocks], np.int64)
        sizes = np.array([b.stored_size for b in model.blocks], np.int64)
        order = np.argsort(offsets)
        start, end = offsets[order], offsets[order] + sizes[order]
        ahead = start < front
        # In front: the last blocks written, one after the other from the end of the
        # index, filling the room to within front_slack.
        assert ahead.any()
        assert start[0] == h["data_offset"] and np.array_equal(start[1:][ahead[1:]], end[:-1][ahead[1:]])
        assert 0 <= front - end[ahead][-1] <= model_assembly.front_slack(int(sizes.sum()))
        # Behind: every other block, one after the other from `front`, as the writer
        # appended them, up to the parts section, which runs to the end of the file.
        assert start[~ahead][0] == front
        assert np.array_equal(start[~ahead][1:], end[~ahead][:-1])
        assert h["parts_size"] > 0 and h["parts_offset"] == end[-1]
        assert h["file_size"] == h["parts_offset"] + h["parts_size"] == path.stat().st_size
    section = read_parts(path)  # the walker's layout checks: no overlaps, zero padding
    assert section is not None and len(section.names) == report["input_parts"]


def test_it_is_the_model_a_whole_write_makes(
    built: tuple[Path, dict], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Without room in front for the index, the build writes the file whole, blocks in
    id order: the same file as the in-place one with its blocks moved into id order."""
    path, _ = built
    monkeypatch.setattr(model_assembly, "front_reserve", lambda triangles: 4096)
    whole = tmp_path / "whole.vast"
    report = build_model(SOURCE, whole, BuildOptions(memory=64 << 20))
    assert not report["blocks_in_place"]
    data = whole.read_bytes()
    assert in_id_order(data) == data  # blocks one after the other, in id order
    assert in_id_order(path.read_bytes()) == data
    # What bench/layout.py compares the layouts with makes the same file.
    assert model_assembly.rewrite_in_id_order(path, tmp_path / "copy.vast") == len(data)
    assert (tmp_path / "copy.vast").read_bytes() == data
    (tmp_path / "copy.vast").unlink()
    assert [f.name for f in tmp_path.iterdir()] == ["whole.vast"]  # no partial or copy left
    # The native reader behind the block cache reads both to the same pixels.
    for a, b in zip(frames(path), frames(whole), strict=True):
        assert np.array_equal(a.prim, b.prim) and np.array_equal(a.depth, b.depth)


@pytest.mark.parametrize("source", ["scene:plant:1000:1", "scene:spheres:5000:2"])
def test_a_small_build_is_written_whole(tmp_path: Path, source: str) -> None:
    """A model smaller than the room in front (one that would leave more than
    front_slack of it empty, and one that would not) is written whole, with no gap, as
    before."""
    out = tmp_path / "small.vast"
    report = build_model(source, out, BuildOptions())
    assert not report["blocks_in_place"]
    assert out.stat().st_size < model_assembly.front_reserve(report["triangles"])
    data = out.read_bytes()
    assert in_id_order(data) == data
    read_parts(out)  # the walker's layout checks
    with ModelFile(out) as model:
        model.verify()


_FULL_DISK_CHILD = """
import resource, signal, sys
from vastray.build import BuildOptions, build_model
phases = []
signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
resource.setrlimit(resource.RLIMIT_FSIZE, (1 << 20, 1 << 20))
try:
    options = BuildOptions(memory=64 << 20)
    build_model(sys.argv[1], sys.argv[2], options, progress=lambda p: phases.append(p.phase))
except Exception as e:
    print(phases[-1], type(e).__name__, e, flush=True)
"""


def test_a_failed_write_of_a_block_fails_the_build_cleanly(tmp_path: Path) -> None:
    """The blocks are written by a thread of the writer's own: when its write fails
    (a file-size limit, as on a full disk), the build stops in its build phase with the
    system's error and the file's name, and leaves nothing behind."""
    ply = tmp_path / "plant.ply"  # read in place: a scene source would stage it first
    scene = [sys.executable, "-m", "vastray", "scene", "plant", "--triangles", "120000", "-o", str(ply)]
    subprocess.run(scene, check=True, capture_output=True)
    out = tmp_path / "out"
    out.mkdir()
    result = subprocess.run(
        [sys.executable, "-c", _FULL_DISK_CHILD, str(ply), str(out / "m.vast")],
        cwd=tmp_path, capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert result.returncode == 0, result.stderr
    assert result.stdout.startswith("build RuntimeError "), result.stdout
    assert "m.vast.partial-" in result.stdout and "write failed: File too large" in result.stdout
    assert os.listdir(out) == []


@pytest.mark.parametrize("offset", [0, 100])
def test_the_writer_takes_only_page_aligned_room(tmp_path: Path, offset: int) -> None:
    """Direct writes start on a 4 KiB page, past the header and the index."""
    with pytest.raises(ValueError, match="multiple of 4096"):
        native.ModelWriter(has_colours=False, output=str(tmp_path / "m.vast"), output_offset=offset)
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize(
    "options",
    [{}, {"tier_width": 0, "compact_triangles": True, "quantized_vertices": True}],
    ids=["default", "small"],
)
def test_a_file_holds_no_more_zeros_than_its_slack(tmp_path: Path, options: dict) -> None:
    """Whatever the layout, a model's file is its header, index, blocks and parts, with
    at most front_slack zero bytes between them: 1/256 of the blocks, not 64 KiB, for a
    model of a few MB (the bunny, whose bytes per triangle it would move by up to 1)."""
    out = tmp_path / "bunny.vast"
    build_model(MODELS / "stanford-bunny.obj", out, BuildOptions(**options))
    with ModelFile(out) as model:
        h = model.header
        blocks = sum(b.stored_size for b in model.blocks)
        gap = h["file_size"] - h["data_offset"] - blocks - h["parts_size"]
        assert 0 <= gap <= model_assembly.front_slack(blocks) < model_assembly.FRONT_SLACK
