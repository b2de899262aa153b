"""Coarseness tiers (format version 5, FLAG_TIERED; docs/FORMAT.md §5, §7, §15).

A tiered model splits every level into streams by the radius of the LOD node above each
unit (a sibling pair of treelets, or a leaf's triangles): a view needs a unit exactly
when that node's voxel is too big for its footprint, so a far view needs only the
coarse streams. Checked here, through the independent walker (tests/modelwalk.py):

* every unit sits in the stream of the tier its LOD radius gives (the writer's rule,
  recomputed here), leaves' triangles in the tier of their treelet, the root's in tier
  0; every block holds one tier; within a level, each tier's radii lie below the
  coarser tier's; the level table tiles the index level-major, coarsest tier first;
* a tiered build holds exactly the tree of an untiered build of the same input, node
  for node (only where things are stored differs), in core and out of core, with
  subtrees emitted in parallel and their open triangle blocks merged;
* a far overview completed at PoE 2 uses well under the untiered working set, with the
  same images (at PoE 2 and at full detail); the native decoder agrees;
* the file is byte-identical for 1, 2 and 3 build threads, in core and out of core;
* untiered files relabelled versions 1-4 still read and render the same; a tiered file
  that says version 4, an unknown flag bit, and a damaged tier count are refused with
  errors that say so, by the Python and the native reader.
"""

from __future__ import annotations

import functools
import itertools
import math
import struct
import zlib
from collections import defaultdict
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
from modelwalk import Node, Walker, WalkError
from test_build import SMALL_MEMORY, header_offset, write_soup
from views import render_camera

from vastray import native
from vastray.build import BuildOptions, build_model
from vastray.camera import frame_bounds
from vastray.modelfile import FLAG_TIERED, HEADER_SIZE, MAX_TIERS, VERSION, ModelError, ModelFile
from vastray.outofcore import OutOfCoreModel

WIDTH, COARSE = 1.0, 4  # BuildOptions' tier_width and tier_coarse_octaves (the defaults)


@dataclass
class Pair:
    tiered: Path
    untiered: Path
    report: dict


@pytest.fixture(scope="module")
def workdir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tmp_path_factory.mktemp("tiers")


@pytest.fixture(scope="module")
def pair(workdir: Path) -> Callable[[str], Pair]:
    """Each input built tiered (the default) and untiered, once per module."""
    sources = {
        "plant": ("scene:plant:200000:3", {}),
        "out-of-core": ("scene:plant:100000:2", {"memory": SMALL_MEMORY}),
    }

    @functools.cache
    def get(name: str) -> Pair:
        source, options = sources[name]
        tiered, untiered = workdir / f"{name}.vast", workdir / f"{name}-untiered.vast"
        report = build_model(source, tiered, BuildOptions(**options))
        build_model(source, untiered, BuildOptions(tier_width=0, **options))
        return Pair(tiered, untiered, report)

    return get


def cell_radius(lo: np.ndarray, hi: np.ndarray) -> np.float32:
    """format::cell_radius in float32, term by term as the writer computes it."""
    e = [np.float32(h) - np.float32(lo_) for lo_, h in zip(lo, hi, strict=True)]
    return np.float32(0.5) * np.sqrt(e[0] * e[0] + e[1] * e[1] + e[2] * e[2])


def tier_of(key: float, root_radius: float) -> int:
    """The writer's rule (FORMAT.md §15), from its description: tier 0 down to
    R_root / 2^COARSE, then one tier per WIDTH halvings, the last (63) taking the rest."""
    if math.isinf(key):
        return 0
    anchor = math.ldexp(float(root_radius), -COARSE)
    tier = 0
    while tier < MAX_TIERS - 1 and not key >= anchor * 2.0 ** (-tier * WIDTH):
        tier += 1
    return tier


def keyed_walk(path: Path) -> tuple[ModelFile, Walker, list[tuple[Node, float, float]]]:
    """Every node with its key, the error of the LOD node above its treelet (what that
    node's LOD test compares: its radius without voxel errors), and that node's radius
    (both infinite in the root treelet). Depth first, a treelet's nodes come right after
    the LOD node whose children they are, so that is the last LOD node met one level up."""
    model = ModelFile(path)
    walker = Walker(model)
    last_lod: dict[int, tuple[float, float]] = {}
    out = []
    for node in walker.walk():
        out.append((node, *(last_lod[node.level - 1] if node.level > 0 else (math.inf, math.inf))))
        if node.kind == "lod":
            last_lod[node.level] = (node.error, node.radius)
    return model, walker, out


# ---- the layout --------------------------------------------------------------------------------


@pytest.mark.parametrize("name", ["plant", "out-of-core"])
def test_every_unit_is_in_the_tier_of_the_lod_radius_above_it(pair: Callable[[str], Pair], name: str) -> None:
    model, walker, nodes = keyed_walk(pair(name).tiered)
    h = model.header
    assert model.tiered and h["flags"] & FLAG_TIERED and model.tier_count == h["tier_count"] > 3
    root_radius = cell_radius(np.array(h["cell_lo"]), np.array(h["cell_hi"]))
    tri_level = len(model.levels) - 1
    keys_by_stream: dict[tuple[int, int], list[float]] = defaultdict(list)
    tiers_in_block: dict[int, set[int]] = defaultdict(set)
    by_radius = 0
    for node, key, radius in nodes:
        assert node.tier == tier_of(key, root_radius), (node.level, node.depth, key)
        keys_by_stream[node.level, node.tier].append(key)
        tiers_in_block[node.block].add(node.tier)
        stream = model.stream(node.level, node.tier)
        assert stream.first <= node.block < stream.first + stream.count
        if node.kind == "lod":
            assert node.child_tier == tier_of(node.error, root_radius)
        if node.kind == "leaf":
            # A leaf's triangles need what its treelet needs. In the root treelet of a part
            # built in core below out-of-core treelets, the writer keys them by the radius
            # of the LOD node above: its error depends on parts not yet built (a tier no finer).
            assert node.tri_tier == node.tier or node.tri_tier == tier_of(radius, root_radius)
            by_radius += node.tri_tier != node.tier
            stream = model.stream(tri_level, node.tri_tier)
            assert all(stream.first <= b < stream.first + stream.count for b in node.tri_blocks)
            for b in node.tri_blocks:
                tiers_in_block[b].add(node.tri_tier)
    # Every block is reached, and holds units of one tier.
    assert sorted(walker.raw) == list(range(len(model.blocks)))
    assert all(len(t) == 1 for t in tiers_in_block.values())
    # Coarsest first: within a level, a tier's keys all lie below the next coarser one's.
    for level in range(model.node_levels):
        tiers = sorted(t for lv, t in keys_by_stream if lv == level)
        for a, b in itertools.pairwise(tiers):
            assert min(keys_by_stream[level, a]) > max(keys_by_stream[level, b])
    assert len({t for _, t in keys_by_stream}) > 3
    assert by_radius < 0.01 * sum(node.kind == "leaf" for node, _, _ in nodes)
    model.close()


def test_the_level_table_tiles_the_index_level_major(pair: Callable[[str], Pair]) -> None:
    with ModelFile(pair("plant").tiered) as model:
        t = model.tier_count
        assert len(model.streams) == len(model.levels) * t
        expected = 0
        for i, s in enumerate(model.streams):
            assert (s.level, s.tier, s.first) == (i // t, i % t, expected)
            expected += s.count
        assert expected == len(model.blocks)
        assert (model.stream(0, 0).first, model.stream(0, 0).count) == (0, 1)  # the root, alone
        # Per level, the table's counts add up to what an untiered build counts.
        with ModelFile(pair("plant").untiered) as flat:
            assert not flat.tiered and flat.tier_count == 1
            assert model.level_contents == [*flat.level_contents[:-1], model.level_contents[-1]]
            assert model.level_contents[-1][0] >= flat.level_contents[-1][0]  # triangle records


@pytest.mark.parametrize("name", ["plant", "out-of-core"])
def test_a_tiered_build_holds_the_same_tree(pair: Callable[[str], Pair], name: str) -> None:
    """Tiers change where units are stored, never what they hold: the same nodes, cells,
    voxels and leaf triangles as the untiered build, node for node. `plant` is one part
    emitted as parallel jobs, whose open triangle blocks the merge repacks."""
    p = pair(name)
    if name == "plant":
        assert p.report["incore_parts"] == 1 and p.report["emission_jobs"] > 1
    if name == "out-of-core":
        assert p.report["incore_parts"] > 1
    with ModelFile(p.tiered) as a, ModelFile(p.untiered) as b:
        count = 0
        for x, y in zip(Walker(a).walk(), Walker(b).walk(), strict=True):
            shape = ("kind", "level", "depth", "axis", "split", "radius")
            assert [getattr(x, k) for k in shape] == [getattr(y, k) for k in shape]
            np.testing.assert_array_equal(x.lo, y.lo)
            np.testing.assert_array_equal(x.hi, y.hi)
            assert x.samples == y.samples
            if x.kind == "leaf":
                np.testing.assert_array_equal(x.ids, y.ids)
                np.testing.assert_array_equal(x.vertices, y.vertices)
                np.testing.assert_array_equal(x.colours, y.colours)
            count += 1
        assert count > 1000


# ---- what a view reads -------------------------------------------------------------------------


def test_a_far_view_needs_far_fewer_blocks(pair: Callable[[str], Pair]) -> None:
    p = pair("plant")
    frames = {}
    for key, path in (("tiered", p.tiered), ("untiered", p.untiered)):
        cache = native.BlockCache(128 << 20, 2, "count")
        with OutOfCoreModel(path, cache) as model:
            camera = frame_bounds(*model.bounds, width=320, height=180)
            far = model.render_complete(camera, pixels_of_error=2.0)
            full = model.render_complete(camera, pixels_of_error=0.0)
            frames[key] = (far, full, cache.totals()["bytes_read"])
    (far_t, full_t, read_t), (far_u, full_u, read_u) = frames["tiered"], frames["untiered"]
    assert far_t.complete and far_u.complete and far_t.stats.voxel_hits > 0
    # The far view's blocks: well under the untiered layout's, in bytes and in blocks.
    assert far_t.stats.working_set_bytes < 0.6 * far_u.stats.working_set_bytes, (
        far_t.stats.working_set_bytes, far_u.stats.working_set_bytes)  # fmt: skip
    assert far_t.stats.working_set_blocks < 0.8 * far_u.stats.working_set_blocks
    # Layout changes what is read, never what is drawn.
    for a, b in ((far_t, far_u), (full_t, full_u)):
        np.testing.assert_array_equal(a.prim, b.prim)
        np.testing.assert_array_equal(a.image, b.image)
        np.testing.assert_array_equal(a.depth, b.depth)
    assert read_t > 0 and read_u > 0
    # Full detail out of core is the in-core render of the decoded file (native decoder).
    with ModelFile(p.tiered) as f:
        scene = f.to_scene()
    reference = render_camera(scene, frame_bounds(*ModelFile(p.tiered).bounds, width=320, height=180))
    np.testing.assert_array_equal(full_t.prim, reference.prim)
    np.testing.assert_array_equal(full_t.image, reference.image)


# ---- threads -----------------------------------------------------------------------------------


@pytest.mark.slow
@pytest.mark.parametrize(
    "source, memory",
    [("scene:plant:600000:3", 2 << 30), ("scene:plant:1600000:3", 40 << 20)],
    ids=["in-core", "out-of-core"],
)
def test_tiered_output_does_not_depend_on_the_thread_count(tmp_path: Path, source: str, memory: int) -> None:
    files = []
    for threads in (1, 2, 3):
        out = tmp_path / f"threads-{threads}.vast"
        report = build_model(source, out, BuildOptions(threads=threads, memory=memory))
        assert report["tiers"] > 3 and report["emission_jobs"] > 1, report
        assert (report["incore_parts"] > 1) == (memory < 1 << 30)
        files.append(out.read_bytes())
    assert files[0] == files[1] == files[2]


# ---- versions and damage -----------------------------------------------------------------------


def rewrite_header(path: Path, **fields: int) -> None:
    """Sets u32 header fields (by name, or tier_count at its offset) and recomputes the
    header checksum, so only those fields differ."""
    data = bytearray(path.read_bytes())
    for name, value in fields.items():
        struct.pack_into("<I", data, header_offset(name), value)
    crc_at = header_offset("header_crc32")
    struct.pack_into("<I", data, crc_at, 0)
    struct.pack_into("<I", data, crc_at, zlib.crc32(bytes(data[:HEADER_SIZE])))
    path.write_bytes(bytes(data))


def header_u32(path: Path, name: str) -> int:
    with open(path, "rb") as f:
        f.seek(header_offset(name))
        return struct.unpack("<I", f.read(4))[0]


def refused(path: Path, message: str) -> None:
    """Both readers refuse the file, saying why."""
    with pytest.raises(ModelError, match=message):
        ModelFile(path)
    with pytest.raises((ModelError, RuntimeError, ValueError), match=message):
        OutOfCoreModel(path, native.BlockCache(8 << 20, 1, "count"))


def test_untiered_files_of_every_older_version_still_read(tmp_path: Path) -> None:
    soup = tmp_path / "soup.f32"
    write_soup(soup, np.random.default_rng(7))  # no parts, no colours: what version 1 can hold
    # (and untiered, without quantized splits or packed voxels: nothing of a later version)
    current = tmp_path / "current.vast"
    build_model(soup, current, BuildOptions(tier_width=0, quantized_splits=False, packed_voxels=False))
    camera = frame_bounds(*ModelFile(current).bounds, width=64, height=48)

    def full_detail(path: Path) -> np.ndarray:
        with OutOfCoreModel(path, native.BlockCache(16 << 20, 1, "count")) as model:
            return model.render_complete(camera, pixels_of_error=0.0).prim

    expected = full_detail(current)
    assert (expected >= 0).mean() > 0.1
    for version in range(1, VERSION):
        old = tmp_path / f"v{version}.vast"
        old.write_bytes(current.read_bytes())
        rewrite_header(old, version=version)
        with ModelFile(old) as model:
            assert model.header["version"] == version and not model.tiered and model.tier_count == 1
            model.verify()
        np.testing.assert_array_equal(full_detail(old), expected)


def test_tiered_and_unknown_flags_are_refused_clearly(pair: Callable[[str], Pair], tmp_path: Path) -> None:
    source = pair("plant").tiered
    flags, tiers = header_u32(source, "flags"), header_u32(source, "tier_count")
    assert flags & FLAG_TIERED and tiers > 1

    def variant(name: str, **fields: int) -> Path:
        path = tmp_path / f"{name}.vast"
        path.write_bytes(source.read_bytes())
        rewrite_header(path, **fields)
        return path

    # A tiered file that claims to be version 4 (which had no tiers).
    refused(variant("v4", version=4), "unsupported attribute flags")
    # A flag this version does not know (bit 8).
    refused(variant("bit9", flags=flags | 1 << 9), "unsupported attribute flags")
    # The tier count and the flag disagree, or the count is impossible.
    refused(variant("no-flag", flags=flags & ~FLAG_TIERED), "tier count set without the tiered flag")
    refused(variant("zero", tier_count=0), "implausible tier count")
    refused(variant("too-many", tier_count=MAX_TIERS + 1), "implausible tier count")
    # A newer version is refused by its number, before anything else.
    refused(variant("newer", version=VERSION + 1), rf"format version {VERSION + 1} is not supported")


def test_a_damaged_block_reference_is_named(pair: Callable[[str], Pair]) -> None:
    """A LOD node of the root treelet made to name a tier the model does not have, or a
    block past the end of its stream: the native decoder and the walker both refuse it
    (the out-of-core walk treats such a node like a missing block: lod_traverse.h)."""
    path = pair("plant").tiered
    with ModelFile(path) as model:
        raw = [model.read_block(i) for i in range(len(model.blocks))]
        lod = next(n for n in Walker(model).walk() if n.kind == "lod" and n.level == 0)
        tier, tiers = lod.child_tier, model.tier_count
        first, count = model.stream(1, tier).first, model.stream(1, tier).count
        h = model.header
        for reference, message in (
            (tiers << 26, rf"child block 0 of tier {tiers} is outside level 1"),
            (tier << 26 | count, rf"child block {count} of tier {tier} is outside level 1"),
        ):
            root = bytearray(raw[0])
            # The child block word: word 3 of a LOD node, word 2 with quantized splits (FORMAT.md §8).
            struct.pack_into("<I", root, lod.offset + (8 if model.quantized_splits else 12), reference)
            blocks = [bytes(root), *raw[1:]]
            with pytest.raises(RuntimeError, match=rf"model block 0: {message}"):
                native.decode_model(
                    blocks, [s.first for s in model.streams], list(h["centre"]), list(h["cell_lo"]),
                    list(h["cell_hi"]), h["input_triangles"], model.has_colours, model.quantized_splits,
                    model.quantized_vertices, tiers, True,
                )  # fmt: skip
            walker = Walker(model)
            walker.raw[0] = bytes(root)
            with pytest.raises(WalkError, match=f"names tier {tiers} of {tiers}|outside level 1 tier {tier}"):
                for _ in walker.walk():
                    pass
        assert first >= 1
