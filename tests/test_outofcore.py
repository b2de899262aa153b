"""Rendering built models out of core: the block cache and the LOD renderer on real files.

Small models are built once per module (`vastray.build.build_model`) and rendered
through `native.BlockCache` / `vastray.outofcore.OutOfCoreModel`:

* the cache's bookkeeping over many frames of a moving camera in a cache far smaller
  than the model: the budget is never exceeded, `check_invariants()` holds after every
  frame, loads and evictions account exactly for the change of the resident set, a
  block the frame used is never evicted at its end, and eviction is least recently used
  (checked per frame from the `resident()` stamps, and on three views of separate tiles:
  the blocks of the least recently used view go first, not those loaded first);
* the fetch queue's bounds, closing a model with fetches in flight, bad view parameters;
* four Python threads rendering two models in one shared cache that cannot hold both;
  afterwards each model's full-detail image still equals its decoded reference;
* a corrupted block (a node block, a triangle block, the root) is reported by name,
  never requested again, and drawn as the voxels above it; other models in the cache
  are unaffected; bad files fail to open with a `ModelError` that says why;
* at PoE 0 a complete frame is exactly the in-core render of the same file decoded
  (`ModelFile.to_scene`), for a coloured model, an uncoloured one and one built out of
  core, in every shading mode; and agrees with the kd-tree built from the mesh;
* the image error falls as the pixels of error fall;
* the first frame is drawn at once from voxels that cover the model, and refining never
  changes a pixel that already shows a triangle or the background;
* the numerical extremes of tests/test_extremes.py through the out-of-core path: models
  far from the origin and at huge and tiny scales, degenerate triangles, rays along the
  axes through a box's edges and faces, the camera inside a closed model, sun shadows on
  a sphere far from the origin;
* `vastray render MODEL.vast --poe --cache`, and its error for a cache too small.

Two tests pin bugs found while writing them: the working-set statistics left out blocks
published at the frame's start, and a preload larger than the cache evicted the
model's own root.
"""

from __future__ import annotations

import dataclasses
import functools
import itertools
import math
import re
import shutil
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import pytest
import trimesh
from PIL import Image
from test_build import SMALL_MEMORY, flip_bit, rewrite_version, run_cli
from test_extremes import CAMERA, TRANSFORMS, degenerate_scene, view_directions
from views import render_camera, render_view

import vastray.render as vrender
from vastray import native, outofcore
from vastray.build import BuildOptions, build_model
from vastray.camera import Camera, frame_bounds
from vastray.modelfile import HEADER_SIZE, VERSION, ModelError, ModelFile
from vastray.outofcore import CacheTooSmallError, OutOfCoreModel, make_cache
from vastray.pagecache import drop_page_cache, resident_fraction
from vastray.renderer import PRIM_VOXEL, Frame, render_params

if TYPE_CHECKING:
    from conftest import ModelMesh

SLOT = 65536
BIG = 64 << 20  # a cache that holds every model of this module whole
SHADINGS = ("headlight", "normal", "sun", "ao", "indirect")


# ---- inputs and built models ---------------------------------------------------------------------


def write_ply(path: Path, vertices: np.ndarray, faces: np.ndarray) -> Path:
    """Binary PLY with float64 vertices (so translated models keep their precision)."""
    header = (
        "ply\nformat binary_little_endian 1.0\n"
        f"element vertex {len(vertices)}\nproperty double x\nproperty double y\nproperty double z\n"
        f"element face {len(faces)}\nproperty list uchar int vertex_indices\nend_header\n"
    )
    records = np.zeros(len(faces), dtype=[("n", "u1"), ("v", "<i4", (3,))])
    records["n"] = 3
    records["v"] = faces
    with open(path, "wb") as f:
        f.write(header.encode("ascii"))
        f.write(np.ascontiguousarray(vertices, dtype="<f8").tobytes())
        f.write(records.tobytes())
    return path


TILE_GAP = 3.0


def write_tiles(path: Path, n: int = 100, count: int = 3) -> Path:
    """`count` wavy unit tiles (n x n quads each) side by side along x, TILE_GAP apart:
    a camera above one tile sees nothing of the others, so the views of different tiles
    share only the top of the tree."""
    xs = np.linspace(0.0, 1.0, n + 1)
    x, y = np.meshgrid(xs, xs, indexing="xy")
    tiles = []
    for k in range(count):
        p = np.stack([x + k * TILE_GAP, y, 0.05 * np.sin(12 * x + k) * np.cos(9 * y)], axis=-1)
        p00, p10, p01, p11 = p[:-1, :-1], p[:-1, 1:], p[1:, :-1], p[1:, 1:]
        tiles += [
            np.stack([p00, p10, p11], -2).reshape(-1, 3, 3),
            np.stack([p00, p11, p01], -2).reshape(-1, 3, 3),
        ]
    np.concatenate(tiles).astype("<f4").tofile(path)
    return path


def tile_camera(k: int, width: int = 48, height: int = 36) -> Camera:
    centre = (0.5 + TILE_GAP * k, 0.5, 0.0)
    return Camera((centre[0], centre[1], 1.6), centre, (0.0, 1.0, 0.0), 40.0, width, height)


@dataclass
class Built:
    name: str
    path: Path
    report: dict[str, Any]

    @cached_property
    def decoded(self) -> native.Scene:
        """The same file decoded whole: the in-core reference."""
        with ModelFile(self.path) as model:
            return model.to_scene()

    @cached_property
    def bounds(self) -> tuple[list[float], list[float]]:
        with ModelFile(self.path) as model:
            return model.bounds

    @cached_property
    def levels(self) -> list[tuple[int, int]]:
        with ModelFile(self.path) as model:
            return model.levels

    def camera(self, width: int = 96, height: int = 72, **kwargs: Any) -> Camera:
        return frame_bounds(*self.bounds, width=width, height=height, **kwargs)


@pytest.fixture(scope="module")
def workdir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tmp_path_factory.mktemp("outofcore")


@pytest.fixture(scope="module")
def bunny_mesh(models_folder: Path, load_model: Callable[[Path], ModelMesh]) -> ModelMesh:
    path = models_folder / "stanford-bunny.obj"
    if not path.exists():
        pytest.fail(f"{path} missing")
    return load_model(path)


@pytest.fixture(scope="module")
def built(workdir: Path, bunny_mesh: ModelMesh) -> Callable[[str], Built]:
    """Builds each model once per module, on first use:
    plant       60k coloured triangles, 11 levels
    big-plant   200k coloured triangles, 256 blocks (137 untiered)
    big-plant-untiered  the same, one stream per level (a view at PoE 0 reads most blocks)
    bunny       the Stanford bunny, no colours (from a float64 PLY)
    out-of-core a 60k plant built with the smallest memory budget (split on disk)
    tiles       three separate tiles (60k triangles) for views with disjoint blocks"""
    sources: dict[str, tuple[Callable[[], str | Path], BuildOptions]] = {
        "plant": (lambda: "scene:plant:60000:3", BuildOptions()),
        "big-plant": (lambda: "scene:plant:200000:3", BuildOptions()),
        "big-plant-untiered": (lambda: "scene:plant:200000:3", BuildOptions(tier_width=0)),
        "bunny": (
            lambda: write_ply(workdir / "bunny.ply", bunny_mesh.vertices, bunny_mesh.faces),
            BuildOptions(),
        ),
        "out-of-core": (lambda: "scene:plant:60000:2", BuildOptions(memory=SMALL_MEMORY)),
        "tiles": (lambda: write_tiles(workdir / "tiles.f32"), BuildOptions()),
    }

    @functools.cache
    def get(name: str) -> Built:
        source, options = sources[name]
        path = workdir / f"{name}.vast"
        return Built(name, path, build_model(source(), path, options))

    return get


# ---- helpers ---------------------------------------------------------------------------------------


def reference(built: Built, camera: Camera, shading: str = "headlight") -> Frame:
    return render_camera(built.decoded, camera, shading=shading)


def render_until_complete(
    model: native.CachedModel, cache: native.BlockCache, camera: Camera, poe: float = 0.0, frames: int = 200
) -> Frame:
    """Native frames until one is complete, draining the fetchers between frames."""
    for _ in range(frames):
        out = render_camera(model, camera, pixels_of_error=poe)
        if out.complete:
            return out
        cache.drain()
    raise AssertionError(f"not complete after {frames} frames: {out.stats}")


def stamps(model: native.CachedModel) -> dict[int, int]:
    return dict(model.resident())


def check_totals(cache: native.BlockCache, models: list[native.CachedModel] | None = None) -> dict[str, Any]:
    t = cache.totals()
    assert cache.check_invariants() == ""
    assert t["slot_count"] * SLOT <= t["budget_bytes"]
    assert t["resident_blocks"] <= t["slot_count"]
    assert t["resident_bytes"] <= t["resident_blocks"] * SLOT
    # Every slot is exactly one of resident, free, retired, being loaded or loaded unpublished.
    assert (
        t["resident_blocks"] + t["free_slots"] + t["retired_slots"] + t["loading"] + t["ready"]
        == t["slot_count"]
    )
    if models is not None:
        assert sum(len(m.resident()) for m in models) == t["resident_blocks"]
    return t


def check_frame_bookkeeping(before: dict[int, int], after: dict[int, int], stats: dict[str, Any]) -> None:
    """One frame of a single model rendered alone, from the resident (block -> stamp)
    maps before and after it: what arrived is what the frame published, what left is
    what it evicted, nothing it used left, and what left was least recently used."""
    tick = stats["tick"]
    arrived, left = after.keys() - before.keys(), before.keys() - after.keys()
    assert len(arrived) == stats["blocks_loaded"], (arrived, stats)
    assert len(left) == stats["blocks_evicted"], (left, stats)
    # Published blocks are stamped with the frame that published them.
    assert all(after[b] == tick for b in arrived)
    # Stamps only move forward, to this frame.
    assert all(after[b] in (before[b], tick) for b in after.keys() & before.keys())
    # Every block the frame used is still there, stamped with its tick; besides them only
    # blocks published at its start carry that stamp.
    used = sum(1 for s in after.values() if s == tick)
    assert stats["working_set_blocks"] <= used <= stats["working_set_blocks"] + stats["blocks_loaded"], stats
    if stats["blocks_loaded"] == 0:
        assert used == stats["working_set_blocks"]
    # Least recently used first: nothing that stayed without being used is older than
    # anything that was evicted.
    if left:
        oldest_kept = min((s for s in after.values() if s != tick), default=math.inf)
        assert max(before[b] for b in left) <= oldest_kept, (sorted(before[b] for b in left), oldest_kept)


# ---- the cache -------------------------------------------------------------------------------------


def test_budget_and_invariants_over_a_moving_camera(built: Callable[[str], Built]) -> None:
    """A 12-slot cache and a model of over 20 times as many blocks (252): orbiting,
    zooming views at PoE 8, 2 and 0, two frames each with the fetchers drained in
    between. Some views need more than the cache holds (every slot then belongs to the
    frame), others let old blocks go."""
    plant = built("big-plant")
    cache = native.BlockCache(12 * SLOT + 1000, fetchers=2)
    assert cache.slot_count == 12
    model = cache.open(str(plant.path))
    assert model.block_count > 20 * cache.slot_count
    lo, hi = np.array(plant.bounds[0]), np.array(plant.bounds[1])
    centre, size = (lo + hi) / 2, hi - lo
    evicted = full = complete = 0
    for i in range(36):
        angle = 2 * math.pi * i / 12
        poe = (8.0, 2.0, 0.0)[i % 3]
        zoom = (1.0, 0.3, 0.1)[(i // 3) % 3]
        middle = centre + size * np.array([0.3 * math.cos(angle), 0.0, 0.3 * math.sin(angle)]) * (1 - zoom)
        camera = frame_bounds(
            middle - size * zoom / 2,
            middle + size * zoom / 2,
            width=48,
            height=36,
            direction=(math.cos(angle), 0.7, math.sin(angle)),
        )
        for _ in range(2):
            before = stamps(model)
            out = render_camera(model, camera, pixels_of_error=poe)
            after = stamps(model)
            s = out.stats.as_dict()
            check_frame_bookkeeping(before, after, s)
            t = check_totals(cache, [model])
            assert t["active_frames"] == 0
            evicted += s["blocks_evicted"]
            full += sum(1 for x in after.values() if x == s["tick"]) == cache.slot_count
            complete += out.complete
            cache.drain()
            check_totals(cache, [model])
    print(f"{evicted} blocks evicted, {full} frames used every slot, {complete} complete")
    # The sequence did what it is meant to exercise.
    assert evicted > 50 and full > 5 and complete > 0, (evicted, full, complete)
    assert cache.totals()["evicted"] == evicted
    model.close()
    t = check_totals(cache)
    assert t["resident_blocks"] == 0 and t["models"] == 0


def test_eviction_is_least_recently_used(built: Callable[[str], Built]) -> None:
    """Views A, B and C of three separate tiles share only the top of the tree. A and then
    B are rendered to completion in a cache that holds both, then A once more (loading
    nothing): B is now the least recently used view, though A's blocks were loaded first.
    C then needs k slots more than are free: the k blocks that go are the oldest of those
    only B used; none of A's, and not the ones C shares with the others."""
    tiles = built("tiles")
    cache = native.BlockCache(BIG, fetchers=2)
    probe = cache.open(str(tiles.path))
    working: list[set[int]] = []
    for k in range(3):
        out = render_until_complete(probe, cache, tile_camera(k))
        working.append({b for b, s in probe.resident() if s == out.stats.tick})
    probe.close()
    a, b, c = working
    assert len(a - b - c) >= 6 and len(b - a - c) >= 6 and len(c - a - b) >= 6, (a, b, c)
    assert a & b & c  # the top of the tree

    need = len(b - a - c) // 2
    cache = native.BlockCache((len(a | b) + len(c - a - b) - need) * SLOT, fetchers=2)
    model = cache.open(str(tiles.path))
    ticks = [render_until_complete(model, cache, tile_camera(k)).stats.tick for k in (0, 1)]
    again = render_camera(model, tile_camera(0), pixels_of_error=0.0)
    assert again.complete and again.stats.blocks_loaded == 0
    resident = stamps(model)
    assert resident.keys() == a | b and cache.totals()["evicted"] == 0
    # B's own blocks were last used while B was rendered, A's blocks just now.
    assert all(ticks[0] < resident[x] <= ticks[1] for x in b - a)
    assert all(resident[x] == again.stats.tick for x in a)

    evicted: set[int] = set()
    for _ in range(200):
        before = stamps(model)
        out = render_camera(model, tile_camera(2), pixels_of_error=0.0)
        after = stamps(model)
        check_frame_bookkeeping(before, after, out.stats.as_dict())  # least recently used, frame by frame
        check_totals(cache, [model])
        evicted |= before.keys() - after.keys()
        if out.complete:
            break
        cache.drain()
    assert out.complete
    assert evicted <= b - a - c, f"evicted {sorted(evicted)}; only B used {sorted(b - a - c)}"
    assert len(evicted) == need
    oldest_first = sorted(b - a - c, key=lambda x: (resident[x], x))
    assert max(resident[x] for x in evicted) <= resident[oldest_first[need - 1]]
    assert stamps(model).keys() == (a | b | c) - evicted


def test_working_set_counts_blocks_published_at_frame_start(built: Callable[[str], Built]) -> None:
    """The last frame of a render to completion usually publishes the blocks that complete
    it; the same view rendered again uses the same blocks, so both must report the same
    working set."""
    plant = built("plant")
    cache = native.BlockCache(BIG)
    model = cache.open(str(plant.path))
    camera = plant.camera(64, 48)
    last = render_until_complete(model, cache, camera)
    again = render_camera(model, camera, pixels_of_error=0.0)
    assert last.stats.blocks_loaded > 0 and again.stats.blocks_loaded == 0
    assert np.array_equal(last.prim, again.prim)
    used = sum(1 for _, s in model.resident() if s == again.stats.tick)
    assert again.stats.working_set_blocks == used
    assert last.stats.working_set_blocks == again.stats.working_set_blocks
    assert last.stats.working_set_bytes == again.stats.working_set_bytes


def test_cache_parameters_and_closing(built: Callable[[str], Built]) -> None:
    with pytest.raises(ValueError, match="at least 4 blocks"):
        native.BlockCache(4 * SLOT - 1)
    with pytest.raises(ValueError, match="priority"):
        make_cache(1 << 20, priority="random")
    cache = make_cache(4 * SLOT, fetchers=1)
    assert cache.slot_count == 4
    plant = built("plant")
    with OutOfCoreModel(plant.path, cache) as model:
        t = check_totals(cache)
        # The root and the two levels below it, one block each.
        assert t["resident_blocks"] == 3 and t["models"] == 1 and plant.levels[3][0] == 3
        frame = model.render(plant.camera(32, 24), pixels_of_error=0.0)
        assert not frame.complete
        check_totals(cache)
        with pytest.raises(ValueError, match="pixels of error"):
            model.render(plant.camera(32, 24), pixels_of_error=-1.0)
    t = check_totals(cache)
    assert t["resident_blocks"] == 0 and t["models"] == 0 and t["free_slots"] == 4
    with pytest.raises(RuntimeError, match="closed"):
        model.render(plant.camera(32, 24))


def test_preloading_more_than_fits_keeps_the_root(built: Callable[[str], Built]) -> None:
    """Opening loads the root; a preload of more levels than the cache holds loads the
    coarsest blocks that fit and skips the rest (block_cache.h), so the first frame still
    draws voxels over the whole model."""
    plant = built("plant")
    camera = plant.camera(64, 48)
    full = reference(plant, camera)
    cache = make_cache(4 * SLOT)
    with OutOfCoreModel(plant.path, cache, preload_levels=10) as model:
        first = model.render(camera, pixels_of_error=0.0)
        resident = cache.totals()["resident_blocks"]
        assert not (first.prim[full.prim >= 0] == -1).any(), "the first frame lost the model"
        assert first.stats.voxel_hits > 0 and resident == 4


def test_close_with_fetches_in_flight(built: Callable[[str], Built]) -> None:
    plant = built("plant")
    cache = make_cache(BIG, fetchers=1)
    camera = plant.camera(64, 48)
    model = OutOfCoreModel(plant.path, cache)
    frame = model.render(camera, pixels_of_error=0.0)
    assert frame.stats.pending > 0
    model.close()
    model.close()  # twice is fine
    check_totals(cache)
    cache.drain()
    t = check_totals(cache)
    assert t["models"] == 0 and t["resident_blocks"] == 0 and t["free_slots"] == t["slot_count"]
    with OutOfCoreModel(plant.path, cache) as again:
        np.testing.assert_array_equal(
            again.render_complete(camera, pixels_of_error=0.0).prim, reference(plant, camera).prim
        )


def test_request_queue_is_bounded(built: Callable[[str], Built]) -> None:
    """A frame adds at most max_requests_per_frame blocks to the fetch queue, which never
    holds more than max_pending; the view still completes, a few blocks per frame."""
    with pytest.raises(ValueError, match="max_pending"):
        native.BlockCache(BIG, 2, "count", 8, 4)
    plant = built("big-plant")
    cache = native.BlockCache(BIG, 1, "count", max_requests_per_frame=4, max_pending=8)
    model = cache.open(str(plant.path))
    camera = plant.camera(64, 48)
    frames = 0
    while True:
        out = render_camera(model, camera, pixels_of_error=0.0)
        frames += 1
        t = check_totals(cache, [model])
        # The queue was empty before the frame (drained): all of it is this frame's.
        assert t["pending"] + t["loading"] + t["ready"] <= 4 and out.stats.pending <= 4
        if out.complete:
            break
        assert frames < 500
        cache.drain()
    assert frames > 100 // 4  # more than 100 blocks, at most 4 a frame
    np.testing.assert_array_equal(out.prim, reference(plant, camera).prim)

    # A cache filled exactly with the top six levels, every block of which each full view
    # uses: nothing can load, and the frames' requests pile up to max_pending, no further.
    top = plant.levels[6][0]
    cache = native.BlockCache(top * SLOT, 1, "count", max_requests_per_frame=4, max_pending=8)
    model = cache.open(str(plant.path))
    assert model.preload_levels(6) == top - 1 and cache.totals()["free_slots"] == 0
    most = 0
    for i in range(12):
        camera = plant.camera(32, 24, direction=(math.cos(i), 0.5, math.sin(i)))
        out = render_camera(model, camera, pixels_of_error=0.0)
        assert out.stats.blocks_requested > 8
        t = check_totals(cache, [model])
        assert t["pending"] <= 8
        most = max(most, t["pending"])
    assert most == 8


# ---- concurrency -----------------------------------------------------------------------------------


def test_threads_render_two_models_in_one_cache(built: Callable[[str], Built]) -> None:
    """Four threads, two per model, orbit and zoom at several PoE and shading modes in a
    cache that holds either model's full-detail view but not both."""
    plant, bunny = built("plant"), built("bunny")
    budget_slots = 64
    cache = make_cache(budget_slots * SLOT, fetchers=3)
    models = [OutOfCoreModel(plant.path, cache), OutOfCoreModel(bunny.path, cache)]
    # Together the two full-detail views need more than the cache holds.
    sizes = []
    for source in (plant, bunny):
        with OutOfCoreModel(source.path, make_cache(BIG)) as probe:
            probe.render_complete(source.camera(64, 48), pixels_of_error=0.0)
            sizes.append(probe.render(source.camera(64, 48), pixels_of_error=0.0).stats.working_set_blocks)
    assert max(sizes) < budget_slots < sum(sizes), sizes

    errors: list[BaseException] = []
    counts = [0] * 4
    broken: list[str] = []

    def work(t: int) -> None:
        model, source = models[t % 2], (plant, bunny)[t % 2]
        lo, hi = np.array(source.bounds[0]), np.array(source.bounds[1])
        try:
            for f in range(30):
                angle = 0.7 * f + 1.3 * t
                zoom = (1.0, 0.5, 0.25)[f % 3]
                middle = (lo + hi) / 2
                camera = frame_bounds(
                    middle - (hi - lo) * zoom / 2,
                    middle + (hi - lo) * zoom / 2,
                    width=48,
                    height=36,
                    direction=(math.cos(angle), 0.5, math.sin(angle)),
                )
                frame = model.render(
                    camera, shading=SHADINGS[f % 4], pixels_of_error=(0.0, 1.0, 4.0)[f % 3], ao_samples=2
                )
                assert frame.image.shape == (36, 48, 3)
                assert (frame.prim >= -2).all()
                counts[t] += 1
                message = cache.check_invariants()
                if message:
                    broken.append(message)
                cache.wait_for_fetches(5.0)
        except BaseException as e:  # reported by the main thread
            errors.append(e)

    threads = [threading.Thread(target=work, args=(t,)) for t in range(4)]
    for th in threads:
        th.start()
    for th in threads:
        th.join(timeout=300)
    assert not any(th.is_alive() for th in threads)
    assert not errors, errors
    assert not broken, broken
    assert counts == [30] * 4
    t = check_totals(cache)
    assert t["active_frames"] == 0 and t["models"] == 2
    assert t["evicted"] > 0  # the models competed for slots

    for model, source in zip(models, (plant, bunny), strict=True):
        camera = source.camera(64, 48)
        frame = model.render_complete(camera, pixels_of_error=0.0)
        ref = reference(source, camera)
        assert frame.complete
        np.testing.assert_array_equal(frame.prim, ref.prim)
        np.testing.assert_array_equal(frame.image, ref.image)
        check_totals(cache)
    for model in models:
        model.close()
    assert check_totals(cache)["resident_blocks"] == 0


# ---- damaged blocks and bad files ------------------------------------------------------------------


@pytest.mark.parametrize("where", ["node level 1", "triangles", "root"])
def test_corrupted_block_is_drawn_as_voxels_and_reported(
    built: Callable[[str], Built], tmp_path: Path, where: str
) -> None:
    plant = built("plant")
    camera = plant.camera()
    good = reference(plant, camera)
    if where == "root":
        block = 0
    elif where == "node level 1":
        block = plant.levels[1][0]
    else:
        # A triangle block this view reads (any ray that reads it changes when it is bad).
        probe_cache = native.BlockCache(BIG)
        probe = probe_cache.open(str(plant.path))
        tick = render_until_complete(probe, probe_cache, camera).stats.tick
        tri_first = plant.levels[-1][0]
        block = min(b for b, s in probe.resident() if s == tick and b >= tri_first)
        probe.close()
    level = next(i for i, (first, count) in enumerate(plant.levels) if first <= block < first + count)
    # named as inspect numbers them
    level_name = "triangle level" if level == len(plant.levels) - 1 else f"LOD level {level}"
    damaged = tmp_path / "damaged.vast"
    shutil.copyfile(plant.path, damaged)
    with ModelFile(damaged) as model_file:
        entry = model_file.blocks[block]
    flip_bit(damaged, entry.offset + entry.stored_size // 2)

    cache = make_cache(BIG)
    other = OutOfCoreModel(plant.path, cache)  # an intact model in the same cache
    with OutOfCoreModel(damaged, cache) as model:
        frame = model.render_complete(camera, timeout=60, pixels_of_error=0.0)
        assert not frame.complete
        assert frame.stats.bad_blocks > 0 and frame.stats.pending == 0
        assert len(model.errors) == 1
        assert re.fullmatch(rf".*\bblock {block} \({level_name}\): checksum mismatch.*", model.errors[0])
        failed = cache.totals()["failed"]
        assert failed == 1
        # Never asked for again.
        for _ in range(3):
            again = model.render(camera, pixels_of_error=0.0)
            assert again.stats.bad_blocks > 0 and not again.complete
            cache.drain()
        assert cache.totals()["failed"] == failed and len(model.errors) == 1
        np.testing.assert_array_equal(again.prim, frame.prim)
        check_totals(cache)

        differ = frame.prim != good.prim
        if where == "root":
            # Nothing above the root to draw: background, and no crash.
            assert (frame.prim == -1).all()
        else:
            assert differ.any()
            # Every pixel that changed shows a voxel above the damaged block; every pixel
            # that hit something still does.
            assert (frame.prim[differ] == PRIM_VOXEL).all()
            assert (frame.prim[good.prim >= 0] != -1).all()
            np.testing.assert_array_equal(frame.image[~differ], good.image[~differ])
            if where == "triangles":
                assert differ.mean() < 0.5  # a local change

        intact = other.render_complete(camera, pixels_of_error=0.0)
        np.testing.assert_array_equal(intact.prim, good.prim)
        np.testing.assert_array_equal(intact.image, good.image)
        assert other.errors == []
    other.close()
    check_totals(cache)


def test_file_truncated_while_open(built: Callable[[str], Built], tmp_path: Path) -> None:
    """Blocks that can no longer be read are bad blocks like corrupted ones."""
    plant = built("plant")
    path = tmp_path / "shrinking.vast"
    shutil.copyfile(plant.path, path)
    camera = plant.camera(64, 48)
    good = reference(plant, camera)
    with OutOfCoreModel(path, make_cache(BIG)) as model:
        _truncate(path, path.stat().st_size // 2)
        frame = model.render_complete(camera, timeout=60, pixels_of_error=0.0)
        assert not frame.complete and frame.stats.bad_blocks > 0
        assert model.errors and all(
            re.match(r"block \d+ \((LOD level \d+|triangle level)\): read failed", e) for e in model.errors
        )
        check_totals(model.cache)
    differ = frame.prim != good.prim
    assert differ.any() and (frame.prim[differ] == PRIM_VOXEL).all()


def _truncate(path: Path, size: int) -> None:
    with open(path, "r+b") as f:
        f.truncate(size)


BAD_FILES: dict[str, tuple[Callable[[Path], None], str]] = {
    "truncated by one byte": (lambda p: _truncate(p, p.stat().st_size - 1), "truncated"),
    "truncated inside the header": (lambda p: _truncate(p, 100), "truncated"),
    "empty": (lambda p: _truncate(p, 0), "not a vastray model"),
    "not a model": (lambda p: p.write_bytes(b"ply\nformat ascii 1.0\n" + bytes(300)), "not a vastray model"),
    "other version": (
        lambda p: rewrite_version(p, VERSION + 1),
        f"format version {VERSION + 1} is not supported",
    ),
    "flipped header bit": (lambda p: flip_bit(p, 40), "header checksum mismatch"),
    "flipped index bit": (lambda p: flip_bit(p, HEADER_SIZE + 30), "index checksum mismatch"),
    "missing": (lambda p: p.unlink(), "cannot open"),
}


@pytest.mark.parametrize("damage", BAD_FILES.keys())
def test_bad_file_fails_to_open(built: Callable[[str], Built], tmp_path: Path, damage: str) -> None:
    path = tmp_path / "model.vast"
    shutil.copyfile(built("plant").path, path)
    change, message = BAD_FILES[damage]
    change(path)
    cache = make_cache(1 << 20)
    with pytest.raises(ModelError, match=message) as info:
        OutOfCoreModel(path, cache)
    assert str(path) in str(info.value)
    t = check_totals(cache)
    assert t["models"] == 0 and t["resident_blocks"] == 0


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"eye": [math.nan, 0.0, 0.0]}, "finite"),
        ({"target": [3.0, -4.0, 2.0]}, "eye and target"),
        ({"up": [-3.0, 4.0, -0.5]}, "parallel"),
        ({"fov": 180.0}, "fov"),
        ({"width": 0}, "size"),
        ({"sun": [0.0, 0.0, 0.0]}, "sun"),
        ({"ao_samples": 0}, "ao_samples"),
        ({"shading": "phong"}, "phong"),
        ({"pixels_of_error": math.nan}, "pixels of error"),
        ({"pixels_of_error": math.inf}, "pixels of error"),
        ({"solid_angle": 7.0}, "solid angle"),
    ],
)
def test_bad_view_raises_and_leaves_the_cache_intact(
    built: Callable[[str], Built], change: dict[str, Any], message: str
) -> None:
    """The checks of test_extremes' bad cameras, through the out-of-core renderer: a clear
    ValueError, no frame left open, and the model renders on."""
    cache = native.BlockCache(BIG)
    model = cache.open(str(built("plant").path))
    with pytest.raises(ValueError, match=message):
        render_view(model, **{**CAMERA, "pixels_of_error": 0.0, **change})
    t = check_totals(cache, [model])
    assert t["active_frames"] == 0 and t["pending"] == 0
    assert (render_view(model, **CAMERA).prim != -1).any()


# ---- full detail against the in-core renderers -----------------------------------------------------


@pytest.mark.parametrize("shading", SHADINGS)
@pytest.mark.parametrize("name", ["plant", "bunny", "out-of-core"])
def test_full_detail_equals_in_core(built: Callable[[str], Built], name: str, shading: str) -> None:
    """PoE 0 rendered to completion (starting from a fresh cache, so the secondary rays'
    blocks come in too) hits exactly the triangles of the decoded scene, at the same
    depths, with the same colours."""
    model_built = built(name)
    if name == "out-of-core":
        assert model_built.report["incore_parts"] > 1 and model_built.report["out_of_core_levels"] >= 1
    with ModelFile(model_built.path) as f:
        assert f.has_colours == (name != "bunny")
    for direction in ((1.0, 0.7, 1.3), (-0.6, -0.5, -1.0)):
        camera = model_built.camera(direction=direction)
        with OutOfCoreModel(model_built.path, make_cache(BIG)) as model:
            frame = model.render_complete(camera, shading=shading, ao_samples=4, pixels_of_error=0.0)
        ref = render_camera(model_built.decoded, camera, shading=shading, ao_samples=4)
        assert frame.complete and frame.stats.voxel_hits == 0 and frame.stats.bad_blocks == 0
        assert (ref.prim >= 0).mean() > 0.1
        np.testing.assert_array_equal(frame.prim, ref.prim)
        np.testing.assert_array_equal(frame.depth, ref.depth)
        if shading in ("headlight", "normal"):
            np.testing.assert_array_equal(frame.image, ref.image)
        else:
            # Shadow and AO rays take another traversal: allow rounding at a few pixels.
            diff = np.abs(frame.image.astype(int) - ref.image.astype(int)).max(axis=2)
            assert (diff > 1).mean() <= 0.002, f"{(diff > 1).sum()} pixels differ, by up to {diff.max()}"
        assert frame.stats.secondary_rays == ref.stats.secondary_rays


@pytest.mark.parametrize("name", ["plant", "out-of-core"])
@pytest.mark.parametrize("interleave_from", ["", "0"])
def test_interleaved_walks_answer_like_one_ray_at_a_time(
    built: Callable[[str], Built], name: str, interleave_from: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    """On a large model (forced here: VASTRAY_INTERLEAVE_BYTES=0) 2x2 and 4x4 packets keep
    several walks in flight per thread: each stops where it would wait for memory and
    another goes on. Their hits, and the single-ray frame's, must be those of the batch
    query, which walks each ray from the root to its end before the next: the same
    triangle at the same distance for every pixel. With level of detail (voxels in the
    image) every packet size gives the single rays' frame."""
    monkeypatch.setenv("VASTRAY_INTERLEAVE_BYTES", interleave_from)
    model_built = built(name)
    camera = model_built.camera(direction=(1.0, 0.7, 1.3))
    origins, directions = camera.primary_rays()
    with OutOfCoreModel(model_built.path, make_cache(BIG)) as model:
        hits = model.pick(origins, directions)
        assert hits.complete.all()
        expected_prim = hits.prim.reshape(camera.height, camera.width)
        assert (expected_prim >= 0).mean() > 0.1
        for packets in (1, 4, 16):
            frame = model.render_complete(camera, pixels_of_error=0.0, packets=packets)
            np.testing.assert_array_equal(frame.prim, expected_prim)
            hit = expected_prim >= 0
            # pick measures t along the unit direction in double; the frame's depth is the
            # renderer's float t along the same ray.
            np.testing.assert_allclose(frame.depth[hit], hits.t.reshape(frame.depth.shape)[hit], rtol=1e-6)
        lod = [model.render_complete(camera, pixels_of_error=4.0, packets=p) for p in (1, 4, 16)]
        assert lod[0].stats.voxel_hits > 0
        for frame in lod[1:]:
            np.testing.assert_array_equal(frame.prim, lod[0].prim)
            np.testing.assert_array_equal(frame.image, lod[0].image)


@pytest.mark.parametrize("tile_size", [4, 16])
def test_tiles_that_miss_the_model_are_background(built: Callable[[str], Built], tile_size: int) -> None:
    """A tile whose rays all miss the model's box is not traced: its pixels are drawn as
    background at once. Every pixel must still be what a walk of its own ray finds (the
    batch query), at tiles of 4 pixels (many of them along the box's outline) and of 16,
    with single rays and packets, out of core and in core; and every ray counts."""
    model_built = built("plant")
    camera = model_built.camera(width=120, height=80, direction=(0.9, 0.35, 0.5))
    origins, directions = camera.primary_rays()
    with OutOfCoreModel(model_built.path, make_cache(BIG)) as model:
        hits = model.pick(origins, directions)
        expected = hits.prim.reshape(camera.height, camera.width)
        background = expected < 0
        tiles = background.reshape(camera.height // 4, 4, camera.width // 4, 4).all(axis=(1, 3))
        assert 0.2 < tiles.mean() < 0.9  # the outline crosses the image
        for packets in (1, 16):
            frame = model.render_complete(camera, pixels_of_error=0.0, packets=packets, tile_size=tile_size)
            np.testing.assert_array_equal(frame.prim, expected)
            assert frame.stats.primary_rays == camera.width * camera.height
            in_core = render_camera(model_built.decoded, camera, packets=packets, tile_size=tile_size)
            np.testing.assert_array_equal(in_core.image, frame.image)
            assert in_core.stats.primary_rays == camera.width * camera.height
        # Background pixels carry the background's colours, row by row.
        top, bottom = frame.image[0][background[0]], frame.image[-1][background[-1]]
        assert len(top) and len(bottom) and (top == top[0]).all() and (bottom == bottom[0]).all()
        assert tuple(top[0]) != tuple(bottom[0])
        # Turned away (the box behind the eye): every tile is background, as every walk finds.
        eye, target = np.asarray(camera.eye), np.asarray(camera.target)
        away = dataclasses.replace(camera, target=tuple(2 * eye - target))
        assert (model.pick(*away.primary_rays()).prim < 0).all()
        turned = model.render_complete(away, pixels_of_error=0.0, tile_size=tile_size)
        assert (turned.prim < 0).all() and turned.stats.node_visits == 0
        assert (turned.image == turned.image[:, :1]).all()  # each row one colour
        assert tuple(turned.image[0, 0]) == tuple(top[0]) and tuple(turned.image[-1, 0]) == tuple(bottom[0])


@pytest.mark.parametrize("name", ["plant", "bunny"])
def test_full_detail_agrees_with_the_mesh_kd_tree(
    built: Callable[[str], Built], bunny_mesh: ModelMesh, name: str
) -> None:
    """Against the in-core kd-tree built from the mesh itself (another tree: only exact
    ties may pick another triangle)."""
    model_built = built(name)
    mesh_scene = (
        vrender.load_model("scene:plant:60000:3").scene
        if name == "plant"
        else native.Scene(bunny_mesh.vertices, bunny_mesh.faces)
    )
    camera = model_built.camera(128, 96)
    with OutOfCoreModel(model_built.path, make_cache(BIG)) as model:
        frame = model.render_complete(camera, pixels_of_error=0.0)
    ref = render_camera(mesh_scene, camera)
    assert (ref.prim >= 0).mean() > 0.1
    assert ((frame.prim >= 0) == (ref.prim >= 0)).mean() >= 0.999
    assert (frame.prim == ref.prim).mean() >= 0.999
    both = (frame.prim >= 0) & (ref.prim >= 0)
    np.testing.assert_allclose(frame.depth[both], ref.depth[both], rtol=1e-5)


def test_priority_by_projected_size_gives_the_same_image(built: Callable[[str], Built]) -> None:
    plant = built("plant")
    camera = plant.camera(64, 48)
    with OutOfCoreModel(plant.path, make_cache(BIG, priority="size")) as model:
        frame = model.render_complete(camera, pixels_of_error=0.0)
    np.testing.assert_array_equal(frame.prim, reference(plant, camera).prim)


@pytest.mark.parametrize("priority", ["count", "size"])
def test_fetch_order_gives_the_same_image(built: Callable[[str], Built], priority: str) -> None:
    """Fetching blocks of about equal priority in file order (the default) or strictly by
    priority changes when blocks arrive, not the complete frame."""
    plant = built("plant")
    camera = plant.camera()
    frames = []
    for file_order in (True, False):
        cache = native.BlockCache(BIG, 1, priority, file_order=file_order)
        with OutOfCoreModel(plant.path, cache, preload_levels=1) as model:
            frames.append(model.render_complete(camera, pixels_of_error=0.0))
        check_totals(cache)
    np.testing.assert_array_equal(frames[0].image, frames[1].image)
    np.testing.assert_array_equal(frames[0].prim, reference(plant, camera).prim)


@pytest.mark.parametrize("poe", [0.0, 2.0])
def test_discovery_frames_change_only_what_loads_first(
    built: Callable[[str], Built], monkeypatch: pytest.MonkeyPatch, poe: float
) -> None:
    """render_complete finds a cold view's blocks with coarse frames whose rays have the
    full frame's LOD cones, then renders full frames: the frame it returns is the one
    full frames alone give, pixel for pixel (at PoE 0 the in-core render)."""
    plant = built("big-plant")
    camera = plant.camera(130, 97)
    coarse, params = outofcore.discovery_pass(camera.to_native(), render_params(pixels_of_error=poe))
    assert (coarse.width, coarse.height) == (33, 25)
    # cone = PoE x pixel angle, pixel angle = 2 tan(fov/2) / height
    assert params.pixels_of_error / coarse.height == pytest.approx(poe / camera.height)
    frames = {}
    for discovery in (True, False):
        if not discovery:
            monkeypatch.setattr(outofcore, "DISCOVERY_MIN_SIDE", 1 << 30)
        with OutOfCoreModel(plant.path, make_cache(BIG)) as model:
            frames[discovery] = model.render_complete(camera, pixels_of_error=poe)
        assert frames[discovery].complete
    for name in ("image", "depth", "prim"):
        np.testing.assert_array_equal(getattr(frames[True], name), getattr(frames[False], name))
    if poe == 0.0:
        np.testing.assert_array_equal(frames[True].prim, reference(plant, camera).prim)
    else:
        assert frames[True].stats.voxel_hits > 0


def test_cache_too_small_for_the_view(built: Callable[[str], Built]) -> None:
    plant = built("plant")
    cache = make_cache(8 * SLOT)
    with OutOfCoreModel(plant.path, cache) as model:
        with pytest.raises(CacheTooSmallError, match="raise the cache budget"):
            model.render_complete(plant.camera(64, 48), pixels_of_error=0.0)
        # A coarser accuracy fits.
        frame = model.render_complete(plant.camera(64, 48), pixels_of_error=16.0)
        assert frame.complete and frame.stats.voxel_hits > 0
    check_totals(cache)


# ---- level of detail -------------------------------------------------------------------------------


def test_image_error_falls_with_the_pixels_of_error(built: Callable[[str], Built]) -> None:
    plant = built("plant")
    camera = plant.camera()
    with OutOfCoreModel(plant.path, make_cache(BIG)) as model:
        full = model.render_complete(camera, pixels_of_error=0.0)
        rows = []
        for poe in (16.0, 8.0, 4.0, 2.0, 1.0, 0.5, 0.0):
            frame = model.render_complete(camera, pixels_of_error=poe)
            assert frame.complete
            wrong = float((frame.prim != full.prim).mean())
            error = float(np.abs(frame.image.astype(float) - full.image).mean()) / 255.0
            rows.append((poe, wrong, error, frame.stats.voxel_hits, frame.stats.working_set_blocks))
    print(
        "\n".join(f"PoE {r[0]:g}: {r[1]:.4f} other prim, error {r[2]:.4f}, {r[3]} voxel hits" for r in rows)
    )
    for (_, wrong0, error0, _, _), (poe, wrong1, error1, _, _) in itertools.pairwise(rows):
        assert wrong1 <= wrong0 + 0.002 and error1 <= error0 + 0.002, f"error grew at PoE {poe}: {rows}"
    by_poe = {r[0]: r for r in rows}
    assert by_poe[0.5][1] < by_poe[16.0][1] and by_poe[0.5][2] < by_poe[16.0][2]
    assert by_poe[16.0][1] > 0.05  # the coarse end is visibly coarse
    assert by_poe[0.0][1] == 0.0 and by_poe[0.0][3] == 0
    assert by_poe[8.0][3] > 0
    # Coarser views need fewer blocks.
    assert by_poe[16.0][4] < by_poe[0.0][4]


def test_diffuse_rays_read_no_finer_than_the_view(built: Callable[[str], Built]) -> None:
    """The indirect mode's diffuse rays start their cone at the primary ray's footprint,
    so near their origin they look the model up no finer than the primary rays did: at
    PoE > 0 the indirect frame reads about the blocks the headlight frame reads (the
    sun's shadow rays add a few), where rays started as a point went down to the leaves
    around every hit. At PoE 0 nothing changes (tested with the in-core renderer)."""
    plant = built("big-plant")
    camera = plant.camera(width=320, height=240)
    blocks = {}
    with OutOfCoreModel(plant.path, make_cache(BIG)) as model:
        for shading in ("headlight", "sun", "indirect"):
            frame = model.render_complete(camera, pixels_of_error=2.0, shading=shading)
            assert frame.complete
            blocks[shading] = frame.stats.working_set_blocks
        full = model.render_complete(camera, pixels_of_error=0.0).stats.working_set_blocks
    print(blocks, "full detail", full)
    assert blocks["headlight"] < full  # the view is coarser than full detail
    assert blocks["indirect"] <= blocks["sun"] * 1.1 + 2, blocks


def test_first_frame_is_instant_and_refines_in_place(built: Callable[[str], Built]) -> None:
    """The first frame of a freshly opened model is drawn from the preloaded coarse levels
    without waiting for anything: incomplete, made of voxels that cover every pixel the
    full-detail image hits. Later frames refine; a pixel that shows a triangle or the
    background at PoE 0 already shows its final answer."""
    plant = built("plant")
    assert len(plant.levels) > 5
    camera = plant.camera()
    cache = make_cache(BIG)
    with OutOfCoreModel(plant.path, cache) as model:
        frames: list[Frame] = [model.render(camera, pixels_of_error=0.0)]
        first = frames[0]
        assert not first.complete
        assert first.stats.blocks_loaded == 0  # nothing arrived: it did not wait
        assert first.stats.blocks_requested > 0 and first.stats.pending > 0
        assert first.stats.voxel_hits > 0 and (first.prim == PRIM_VOXEL).sum() == first.stats.voxel_hits
        assert cache.wait_for_fetches(60_000.0)  # something was asked for, and arrives
        while not frames[-1].complete:
            assert len(frames) < 100
            cache.wait_for_fetches(1000.0)
            frames.append(model.render(camera, pixels_of_error=0.0))
    final = frames[-1]
    assert len(frames) > 2 and final.stats.voxel_hits == 0
    np.testing.assert_array_equal(final.prim, reference(plant, camera).prim)
    shown, full = first.prim != -1, final.prim != -1
    assert not (full & ~shown).any(), "the first frame misses part of the model"
    iou = (shown & full).sum() / (shown | full).sum()
    assert iou > 0.6, iou  # measured 0.75: voxels three levels down are close to the shape
    for k, frame in enumerate(frames):
        settled = frame.prim != PRIM_VOXEL
        np.testing.assert_array_equal(frame.prim[settled], final.prim[settled], err_msg=f"frame {k}")
        np.testing.assert_array_equal(frame.depth[settled], final.depth[settled], err_msg=f"frame {k}")
        if k:
            assert frame.stats.voxel_hits <= frames[k - 1].stats.voxel_hits


# ---- numerical extremes through the out-of-core path ---------------------------------------------


def build_mesh(tmp_path: Path, name: str, vertices: np.ndarray, faces: np.ndarray) -> Path:
    out = tmp_path / f"{name}.vast"
    build_model(write_ply(tmp_path / f"{name}.ply", vertices, faces), out)
    return out


def render_full(path: Path, camera: Camera, shading: str = "headlight") -> Frame:
    with OutOfCoreModel(path, make_cache(BIG)) as model:
        frame = model.render_complete(camera, shading=shading, pixels_of_error=0.0)
    assert frame.complete and not np.isnan(frame.depth).any()
    return frame


def decoded_render(path: Path, camera: Camera, shading: str = "headlight") -> Frame:
    """The decoded scene's frame through the kd-tree (VASTRAY_PRIMARY=kd), the out-of-core
    walk's in-core twin: the wide BVH may take the other of two triangles hit at the same t."""
    with ModelFile(path) as f, pytest.MonkeyPatch.context() as env:
        env.setenv("VASTRAY_PRIMARY", "kd")
        return render_camera(f.to_scene(), camera, shading=shading)


@pytest.mark.parametrize("transform", TRANSFORMS.keys())
def test_translated_and_scaled_models(
    transform: str, tmp_path: Path, bunny_mesh: ModelMesh, built: Callable[[str], Built]
) -> None:
    """The bunny moved 1e6 and 1e7 away from the origin or scaled by 1e-4 and 1e4, built
    from float64 input: the full-detail frame equals the decoded scene, agrees with the
    kd-tree of the transformed mesh, and shows what the untransformed model shows."""
    scale, distance = TRANSFORMS[transform]
    offset = distance * np.array([0.6, -0.48, 0.64])
    vertices = bunny_mesh.vertices * scale + offset
    path = build_mesh(tmp_path, transform, vertices, bunny_mesh.faces)
    plain = built("bunny")
    base_camera = plain.camera(96, 72, direction=(0.3, 0.4, 1.0))

    def moved(p: tuple[float, float, float]) -> tuple[float, float, float]:
        q = np.asarray(p) * scale + offset
        return (float(q[0]), float(q[1]), float(q[2]))

    camera = Camera(
        moved(base_camera.eye), moved(base_camera.target), base_camera.up, base_camera.fov, 96, 72
    )
    frame = render_full(path, camera)
    hit = frame.prim >= 0
    assert hit.mean() > 0.15

    dec = decoded_render(path, camera)
    np.testing.assert_array_equal(frame.prim, dec.prim)
    np.testing.assert_array_equal(frame.image, dec.image)

    ref = render_camera(native.Scene(vertices, bunny_mesh.faces), camera)
    assert ((ref.prim >= 0) == hit).mean() >= 0.999
    assert (ref.prim == frame.prim).mean() >= 0.999
    both = hit & (ref.prim >= 0)
    diag = float(np.linalg.norm(vertices.max(axis=0) - vertices.min(axis=0)))
    np.testing.assert_allclose(frame.depth[both], ref.depth[both], rtol=1e-5, atol=1e-5 * diag)

    base = render_full(plain.path, base_camera)
    assert (base.prim == frame.prim).mean() >= 0.999
    same = hit & (base.prim == frame.prim)
    np.testing.assert_allclose(frame.depth[same] / scale, base.depth[same], rtol=1e-5)


def test_degenerate_triangles_are_never_hit(tmp_path: Path) -> None:
    """The floor and zero-area triangles of test_extremes: the builder drops the
    degenerate ones, and views straight along the degenerate segments and points (odd
    image sizes put the middle pixel's ray exactly through the target) hit only the floor,
    exactly as the in-core scene of the full input does."""
    vertices, faces, degenerate = degenerate_scene()
    path = build_mesh(tmp_path, "degenerate", vertices, faces)
    with ModelFile(path) as f:
        assert f.header["degenerate"] == len(degenerate) and f.header["triangle_count"] == 2
    scene = native.Scene(vertices, faces)
    targets = [vertices[faces[d, k]] for d in degenerate for k in range(3)]
    views = [((2.0, 1.5, 3.0), (0.0, 0.0, 0.5), (0.0, 0.0, 1.0))]
    for t in targets[::2]:
        views.append(((t[0], t[1], 3.0), tuple(t), (0.0, 1.0, 0.0)))  # straight down through it
        views.append(((t[0], t[1] - 3.0, t[2]), tuple(t), (0.0, 0.0, 1.0)))  # along y, level with it
    for eye, target, up in views:
        camera = Camera(tuple(map(float, eye)), tuple(map(float, target)), up, 50.0, 33, 33)
        frame = render_full(path, camera)
        assert set(np.unique(frame.prim)) <= {-1, 0, 1}
        ref = render_camera(scene, camera)
        np.testing.assert_array_equal(frame.prim, ref.prim)
        np.testing.assert_allclose(frame.depth, ref.depth, rtol=1e-6)


def _box_hits(origins: np.ndarray, dirs: np.ndarray, half: float) -> tuple[np.ndarray, np.ndarray]:
    """Entry distance into the cube [-half, half]^3 in double (inf: no hit)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / dirs
        t0, t1 = (-half - origins) * inv, (half - origins) * inv
        # 0 * inf: a ray parallel to a slab, starting on its boundary, stays in it.
        in_plane = np.isnan(t0) | np.isnan(t1)
        near = np.where(in_plane, -np.inf, np.minimum(t0, t1)).max(axis=1)
        far = np.where(in_plane, np.inf, np.maximum(t0, t1)).min(axis=1)
    hit = (near <= far) & (far > 0)
    return hit, np.where(hit, near, np.inf)


BOX_VIEWS = {
    # eye, target, up, rays that only touch the cube (an edge, or lying in a face plane)
    "down-along-an-edge": ((1.0, 1.0, 5.0), (1.0, 1.0, 0.0), (0.0, 1.0, 0.0), 29),
    "down-onto-a-face": ((0.25, -0.5, 5.0), (0.25, -0.5, 0.0), (0.0, 1.0, 0.0), 0),
    "up-in-a-face-plane": ((-1.0, 0.0, -5.0), (-1.0, 0.0, 0.0), (1.0, 0.0, 0.0), 15),
    "along-x-through-an-edge": ((-5.0, 1.0, -1.0), (0.0, 1.0, -1.0), (0.0, 0.0, 1.0), 29),
    "along-y-onto-a-face-centre": ((0.0, 5.0, 0.0), (0.0, 0.0, 0.0), (0.0, 0.0, -1.0), 0),
}


@pytest.mark.parametrize("name", BOX_VIEWS.keys())
def test_axis_views_of_a_box_with_exact_coordinates(tmp_path: Path, name: str) -> None:
    """A cube [-1, 1]^3 seen exactly along an axis (33 x 33 pixels: the middle row and
    column have exactly zero direction components and lie in the cube's face planes or
    through its edges): no NaN, exactly the decoded scene's answer, every
    ray that clearly enters the cube hits at the right distance and every ray that clearly
    passes it misses."""
    cube = trimesh.creation.box(extents=(2.0, 2.0, 2.0))
    vertices, faces = np.asarray(cube.vertices, dtype=np.float64), np.asarray(cube.faces, dtype=np.uint32)
    path = build_mesh(tmp_path, "cube", vertices, faces)
    eye, target, up, touching = BOX_VIEWS[name]
    camera = Camera(eye, target, up, 60.0, 33, 33)
    frame = render_full(path, camera)
    dec = decoded_render(path, camera)
    np.testing.assert_array_equal(frame.prim, dec.prim)
    np.testing.assert_array_equal(frame.depth, dec.depth)

    origins, dirs = camera.primary_rays()
    assert (dirs == 0).sum() >= 33  # the middle row or column
    clear_hit, _ = _box_hits(origins, dirs, 1.0 - 1e-6)
    maybe_hit, _ = _box_hits(origins, dirs, 1.0 + 1e-6)
    exact_hit, t_exact = _box_hits(origins, dirs, 1.0)
    prim, depth = frame.prim.ravel(), frame.depth.ravel()
    assert clear_hit.sum() > 150
    assert (prim[~maybe_hit] == -1).all()
    # Rays that touch the closed cube only at an edge or lying in a face's plane hit too
    # (the traversal and the watertight test leave no gap), at the exact distance.
    touch = exact_hit & ~clear_hit
    assert touch.sum() == touching
    should_hit = clear_hit | touch
    assert (prim[should_hit] >= 0).all(), f"{(prim[should_hit] < 0).sum()} rays passed through the cube"
    np.testing.assert_allclose(depth[should_hit], t_exact[should_hit], rtol=1e-6)


def test_camera_inside_a_closed_model(
    tmp_path: Path, small_closed_model: ModelMesh, winding_numbers: Callable[..., np.ndarray]
) -> None:
    """From a point inside a closed mesh, six 100-degree views at full detail hit the
    surface at every pixel, exactly as the decoded scene does."""
    mesh = small_closed_model
    centroid = trimesh.Trimesh(mesh.vertices, mesh.faces, process=False).center_mass
    jitter = (np.random.default_rng(0).random((200, 3)) - 0.5) * (mesh.hi - mesh.lo) * 0.5
    candidates = np.vstack([centroid, centroid + jitter])
    inside = candidates[np.abs(winding_numbers(mesh.vertices, mesh.faces, candidates) - 1) < 1e-3]
    assert len(inside)
    eye = inside[0]
    path = build_mesh(tmp_path, mesh.name, mesh.vertices, mesh.faces)
    mesh_scene = native.Scene(mesh.vertices, mesh.faces)
    with OutOfCoreModel(path, make_cache(BIG)) as model:
        for forward, up in view_directions():
            camera = Camera(tuple(eye), tuple(eye + np.array(forward, dtype=float)), tuple(up), 100.0, 32, 24)
            frame = model.render_complete(camera, pixels_of_error=0.0)
            assert frame.complete
            assert (frame.prim >= 0).all(), f"{(frame.prim < 0).sum()} pixels see out of a closed mesh"
            assert np.isfinite(frame.depth).all() and (frame.depth > 0).all()
            np.testing.assert_array_equal(frame.prim, decoded_render(path, camera).prim)
            assert (frame.prim == render_camera(mesh_scene, camera).prim).mean() >= 0.999


@pytest.mark.parametrize(
    ("radius", "centre"), [(1.0, (0.0, 0.0, 0.0)), (40.0, (1e6, -2e6, 5e5))], ids=["unit", "far"]
)
def test_sun_does_not_shadow_a_convex_sphere(
    tmp_path: Path, radius: float, centre: tuple[float, float, float]
) -> None:
    """Sun shading at full detail on a finely tessellated sphere, also far from the
    origin: the shadow rays of the out-of-core traversal never hit the sphere itself, and
    the image is the decoded scene's."""
    sphere = trimesh.creation.icosphere(subdivisions=5, radius=radius)
    vertices = np.asarray(sphere.vertices, dtype=np.float64) + np.array(centre)
    faces = np.asarray(sphere.faces, dtype=np.uint32)
    path = build_mesh(tmp_path, "sphere", vertices, faces)
    eye = np.array(centre) + radius * 3.0 * np.array([0.9, -0.5, 0.2])  # sees the terminator
    camera = Camera(tuple(map(float, eye)), centre, (0.0, 0.0, 1.0), 45.0, 96, 96)
    frame = render_full(path, camera, shading="sun")
    dec = decoded_render(path, camera, shading="sun")
    np.testing.assert_array_equal(frame.prim, dec.prim)
    np.testing.assert_array_equal(frame.image, dec.image)

    hit = frame.prim >= 0
    tri = vertices[faces[frame.prim[hit]].astype(np.int64)]
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    _, dirs = camera.primary_rays()
    normal = np.where(
        (np.einsum("ij,ij->i", normal, dirs.reshape(96, 96, 3)[hit]) > 0)[:, None], -normal, normal
    )
    sun = np.array([0.35, 0.8, 0.5]) / np.linalg.norm([0.35, 0.8, 0.5])
    lam = normal @ sun
    grey = frame.image[hit].astype(float).mean(axis=1)
    lit, unlit = lam > 1e-3, lam <= 0
    assert lit.sum() > 1000 and unlit.sum() > 500
    floor = float(np.median(grey[unlit]))
    assert np.abs(grey[unlit] - floor).max() <= 1.0
    # Lit at a cosine above 0.02 is at least 3 grey levels above the floor (slope ~160).
    shadowed = lit & (grey <= floor + 1.0) & (lam > 0.02)
    assert not shadowed.any(), f"{int(shadowed.sum())} lit pixels are in shadow"
    assert abs(frame.stats.secondary_rays - int((lam > 0).sum())) <= int((np.abs(lam) < 1e-6).sum())


# ---- command line ----------------------------------------------------------------------------------


def test_cli_renders_a_built_model_through_a_small_cache(
    built: Callable[[str], Built], tmp_path: Path
) -> None:
    bunny = built("bunny")
    png, full = tmp_path / "out.png", tmp_path / "full.png"
    args = ["render", str(bunny.path), "--size", "64x48", "--cache", "1M"]
    result = run_cli(*args, "--poe", "2", "-o", str(png), cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    assert "PoE 2: complete after" in result.stdout and "cache 1M" in result.stdout
    image = np.asarray(Image.open(png))
    assert image.shape == (48, 64, 3)
    assert np.any(image != image[:, :1, :], axis=2).mean() > 0.05  # the model is in view

    # The same view at full detail needs more than 16 slots.
    result = run_cli(*args, "-o", str(full), cwd=tmp_path)
    assert result.returncode == 2, result.stdout
    assert "vastray: error:" in result.stderr and "raise the cache budget" in result.stderr
    assert "16 slots" in result.stderr
    assert "Traceback" not in result.stderr
    assert not full.exists()


def _transparent_huge_pages() -> str:
    """The kernel's THP mode: the bracketed word of its setting ('never' when absent)."""
    try:
        setting = Path("/sys/kernel/mm/transparent_hugepage/enabled").read_text()
    except OSError:
        return "never"
    return setting.split("[", 1)[1].split("]", 1)[0] if "[" in setting else "never"


def test_huge_page_slots_change_nothing_but_memory_layout(built: Callable[[str], Built]) -> None:
    """The cache's slots on 2 MiB pages (the default, where the kernel allows it) and on
    ordinary pages: the same frames, bit for bit, at full detail and with LOD; the cache
    says which it got, and a cache asked for small pages never gets huge ones."""
    model_built = built("plant")
    camera = model_built.camera(direction=(1.0, 0.7, 1.3))
    frames = {}
    for huge in (True, False):
        cache = native.BlockCache(BIG, 2, "count", huge_pages=huge)
        assert cache.huge_pages == (huge and _transparent_huge_pages() != "never")
        with OutOfCoreModel(model_built.path, cache) as model:
            frames[huge] = [model.render_complete(camera, pixels_of_error=poe) for poe in (0.0, 2.0)]
    for a, b in zip(frames[True], frames[False], strict=True):
        assert a.complete and b.complete
        np.testing.assert_array_equal(a.prim, b.prim)
        np.testing.assert_array_equal(a.image, b.image)
    assert frames[True][1].stats.voxel_hits > 0


def test_queued_blocks_are_read_ahead(built: Callable[[str], Built]) -> None:
    """A frame's queued blocks are handed to the kernel to read ahead. In a cache too
    small for the view (a quarter of the model's blocks: the fetchers stop when it is
    full), the blocks five frames asked for still reach the page cache with read-ahead;
    without it only what the fetchers read (and the kernel read around it) does. Both
    ways the frames are the same. (An untiered model: this view reads nearly all of it.)"""
    path = built("big-plant-untiered").path
    drop_page_cache(path)
    if not resident_fraction(path) <= 0.2:  # NaN: no mincore here
        pytest.skip("the page cache keeps this file (tmpfs?) or cannot be read: read-ahead cannot show")
    camera = built("big-plant-untiered").camera(direction=(1.0, 0.7, 1.3))
    with ModelFile(path) as f:
        slots = max(8, len(f.blocks) // 4)
    resident, images = {}, {}
    for readahead in (False, True):
        drop_page_cache(path)
        cache = native.BlockCache(slots << 16, 1, "count", readahead=readahead)
        with OutOfCoreModel(path, cache) as model:
            requested = 0
            for _ in range(5):
                frame = model.render(camera, pixels_of_error=0.0, request_limit=4096)
                requested += frame.stats.blocks_requested
                cache.wait_idle(2000)
            # The kernel reads in the background, later still on a loaded machine: wait
            # for the share the assertion asks (without read-ahead it never comes).
            deadline = time.monotonic() + 20.0
            while readahead and resident_fraction(path) <= 0.9 and time.monotonic() < deadline:
                time.sleep(0.05)
            resident[readahead] = resident_fraction(path)
            images[readahead] = frame.image
            assert not frame.complete and requested > 2 * slots
    # (Without it the kernel's own read-ahead around each pread brings in a good share.
    # With it, what the frames asked for: 0.89 of this file's pages in one run on 4
    # December, since read-ahead advice covers the blocks asked for and nothing between
    # them, wherever the file puts them.)
    assert resident[True] > 0.85 and resident[True] > resident[False] + 0.1, resident
    np.testing.assert_array_equal(images[False], images[True])
