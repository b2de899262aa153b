"""Packed treelets (format version 7, FLAG_PACKED_TREELETS, docs/FORMAT.md §7-8): in a
model with quantized splits every node and voxel is a multiple of 4 bytes, so treelets
start on 4-byte boundaries instead of 8 and a LOD word counts its offsets in 4-byte
units. Lossless: the same tree, voxels and triangles in fewer bytes, the same frames.

Checked against the version-6 layout of the same build (`packed_treelets=False`): node
for node by the independent walker (tests/modelwalk.py, which decodes the LOD word from
the specification), frame for frame by the out-of-core renderer, and triangle for
triangle by the full-detail decoder; and a flag that does not fit the file is refused by
both readers."""

from __future__ import annotations

import functools
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from modelwalk import Node, Walker, WalkError
from test_build import SMALL_MEMORY, rewrite_version, run_cli
from test_packed_voxels import complete_frames
from test_tiers import refused, rewrite_header

from vastray import native
from vastray.build import BuildOptions, build_model
from vastray.camera import frame_bounds
from vastray.modelfile import (
    FLAG_PACKED_TREELETS,
    FLAG_QUANTIZED_SPLITS,
    VERSION,
    ModelFile,
)
from vastray.render import trace

SOURCES = {
    "plant": ("scene:plant:60000:3", 2 << 30, {}),
    # Parts emitted in parallel and merged: their LOD words are patched when placed.
    "out-of-core": ("scene:plant:60000:2", SMALL_MEMORY, {}),
    # The smallest layout's options: compact blocks, quantized vertices, untiered.
    "smallest": ("scene:spheres:40000:4", 2 << 30, {"compact_triangles": True, "quantized_vertices": True,
                                                     "tier_width": 0.0, "traversal_cost": 6.0}),
}  # fmt: skip
Pair = tuple[Path, Path]  # packed (version 7), the same build in version 6's layout


@pytest.fixture(scope="module")
def built(tmp_path_factory: pytest.TempPathFactory) -> Callable[[str], Pair]:
    folder = tmp_path_factory.mktemp("treelets")

    @functools.cache
    def get(name: str) -> Pair:
        source, memory, options = SOURCES[name]
        packed, padded = folder / f"{name}.vast", folder / f"{name}-v6.vast"
        # Without voxel errors (version 8's): the padded copy is relabelled as version 6.
        build_model(source, packed, BuildOptions(memory=memory, voxel_errors=False, **options))
        padded_options = BuildOptions(memory=memory, packed_treelets=False, voxel_errors=False, **options)
        build_model(source, padded, padded_options)
        return (packed, padded)

    return get


def nodes(path: Path) -> list[Node]:
    with ModelFile(path) as model:
        return list(Walker(model).walk())


def raw_bytes(model: ModelFile, node_levels: bool) -> int:
    tri_first = model.levels[-1][0]
    return sum(e.raw_size for i, e in enumerate(model.blocks) if (i < tri_first) == node_levels)


@pytest.mark.parametrize("name", list(SOURCES))
def test_the_same_tree_in_fewer_bytes(built: Callable[[str], Pair], name: str) -> None:
    packed, padded = built(name)
    with ModelFile(packed) as p, ModelFile(padded) as v6:
        assert p.header["version"] == v6.header["version"] == VERSION == 8
        assert p.packed_treelets and p.header["flags"] & FLAG_PACKED_TREELETS
        assert not v6.packed_treelets and v6.quantized_splits
        # Only the node levels shrink: 4 bytes of padding after about half the treelets.
        assert raw_bytes(p, False) == raw_bytes(v6, False)
        assert raw_bytes(p, True) < 0.98 * raw_bytes(v6, True)
        assert p.header["file_size"] < v6.header["file_size"]
    # `vastray inspect` says which layout a file has.
    said = {path: run_cli("inspect", str(path), cwd=path.parent).stdout for path in (packed, padded)}
    assert "format version 8, quantized splits (packed treelets)" in said[packed], said[packed]
    assert "quantized splits" in said[padded] and "packed treelets" not in said[padded], said[padded]
    a, b = nodes(packed), nodes(padded)
    assert len(a) == len(b) > 1000
    for x, y in zip(a, b, strict=True):
        where = (x.kind, x.level, x.depth, x.lo.tolist(), x.hi.tolist())
        assert where == (y.kind, y.level, y.depth, y.lo.tolist(), y.hi.tolist())
        if x.kind != "leaf":
            assert (x.axis, x.split, x.empty) == (y.axis, y.split, y.empty)
        if x.kind == "lod":
            assert x.samples == y.samples and x.radius == y.radius
        if x.kind == "leaf":
            np.testing.assert_array_equal(x.ids, y.ids)
            np.testing.assert_array_equal(x.vertices, y.vertices)
    # Treelets start on 4-byte boundaries that are not 8-byte ones: the layout is in use.
    roots = [n.offset for n in a if n.depth == 0 and n.level > 0]
    assert all(o % 4 == 0 for o in roots)
    assert sum(o % 8 == 4 for o in roots) > len(roots) // 10


@pytest.mark.parametrize("name", ["plant", "out-of-core"])
def test_frames_and_the_full_detail_decode_are_the_same(built: Callable[[str], Pair], name: str) -> None:
    packed, padded = built(name)
    shadings = ("headlight", "ao")
    frames = {"packed": complete_frames(packed, shadings), "v6": complete_frames(padded, shadings)}
    for x, y in zip(frames["packed"], frames["v6"], strict=True):
        np.testing.assert_array_equal(x.image, y.image)
        np.testing.assert_array_equal(x.prim, y.prim)
    assert frames["packed"][0].stats.voxel_hits > 1000  # the far frames draw voxels
    with ModelFile(packed) as p, ModelFile(padded) as v6:
        camera = frame_bounds(*p.bounds, width=160, height=120)
        np.testing.assert_array_equal(trace(p.to_scene(), camera).prim, trace(v6.to_scene(), camera).prim)


def test_a_flag_that_does_not_fit_the_file_is_refused(built: Callable[[str], Pair], tmp_path: Path) -> None:
    packed, padded = built("plant")
    with ModelFile(packed) as model:
        flags = model.header["flags"]
    # Packed treelets are defined for quantized splits only.
    alone = tmp_path / "alone.vast"
    alone.write_bytes(packed.read_bytes())
    rewrite_header(alone, flags=flags & ~FLAG_QUANTIZED_SPLITS)
    refused(alone, "packed treelets flag set without quantized splits")
    with pytest.raises(ValueError, match="packed treelets need quantized splits"):
        native.decode_model([], [], [0.0] * 3, [0.0] * 3, [1.0] * 3, 1, False, False, packed_treelets=True)
    # Version 6 had no such flag: a packed file relabelled as version 6 is refused ...
    old = tmp_path / "v6.vast"
    old.write_bytes(packed.read_bytes())
    rewrite_version(old, 6)
    refused(old, "unsupported attribute flags")
    # ... and the version-6 layout relabelled as version 6 reads, node for node.
    padded_copy = tmp_path / "padded.vast"
    padded_copy.write_bytes(padded.read_bytes())
    rewrite_version(padded_copy, 6)
    with ModelFile(padded_copy) as model:
        assert model.header["version"] == 6 and not model.packed_treelets
    assert len(nodes(padded_copy)) == len(nodes(packed))


def test_the_walker_reads_the_flag_only_with_quantized_splits(built: Callable[[str], Pair]) -> None:
    """The walker's own check, past the reader's (whose check the file above fails first)."""
    packed, _ = built("plant")
    with ModelFile(packed) as model:
        model.header["flags"] &= ~FLAG_QUANTIZED_SPLITS
        with pytest.raises(WalkError, match="packed treelets without quantized splits"):
            next(iter(Walker(model).walk()))
