"""The ray-tracing kernels' instruction-set paths, their packets and the indirect mode.

* ISA dispatch: `native.supported_isas()` lists the paths this build and CPU run,
  `native.isa()` the one that runs; `VASTRAY_ISA` forces one, and a name that is not a
  path is an error. Every supported path renders bit-identical frames (in core and out of
  core, every shading mode, packets of 1, 4 and 16, PoE 0 and 2) and answers batch
  queries identically: the kernels use the same float operations in the same order on
  every path. The renderer's own tests (test_render, test_extremes, test_watertight) run
  again on every other path, in a subprocess with VASTRAY_ISA set.
* Packets change speed, never answers: secondary rays (shadow and AO rays in packets
  that share a direction or an origin, out of core the diffuse rays of a pixel block in
  packets whose directions agree in sign) give the same images as single rays, in core and
  out of core at full detail and with LOD; the batch occlusion query, which packs rays
  from one origin, answers as it does for the same rays one by one.
* The indirect mode: deterministic; identical in and out of core at full detail; its
  edge-aware filter equals a numpy reference of it, smooths within surfaces and not across
  them; an open
  floor under the sky alone shows exactly albedo x sky (no noise: every diffuse ray
  escapes), the side that faces away from the sky is black; sample_index draws other
  samples (the noise changes, the geometry does not) and averaging passes converges
  towards a many-sample image.
* request_limit lets one frame queue more requests than the cache's per-frame bound.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import trimesh
from views import DIGEST_SCRIPT, render_camera

from vastray import native
from vastray.build import build_model
from vastray.camera import Camera, frame_bounds
from vastray.modelfile import ModelFile
from vastray.outofcore import OutOfCoreModel, make_cache
from vastray.renderer import average_passes

REPO = Path(__file__).resolve().parents[1]
SHADINGS = ("normal", "headlight", "sun", "ao", "indirect")


@pytest.fixture(scope="module")
def plant_model(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("kernels") / "plant.vast"
    build_model("scene:plant:60000:3", path)
    return path


def run_python(code: str, *args: str, isa: str | None = None) -> subprocess.CompletedProcess[str]:
    env = dict(os.environ)
    env.pop("VASTRAY_ISA", None)
    if isa is not None:
        env["VASTRAY_ISA"] = isa
    return subprocess.run(
        [sys.executable, "-c", code, *args], capture_output=True, text=True, env=env, timeout=600
    )


# ---- dispatch ----------------------------------------------------------------------------


def test_paths_are_listed_and_can_be_forced() -> None:
    supported = native.supported_isas()
    assert supported[0] == "sse2" and set(supported) <= {"sse2", "avx", "avx2", "avx512"}
    assert native.isa() in supported
    if "VASTRAY_ISA" not in os.environ:
        assert native.isa() == supported[-1], "the best supported path runs by default"
    for isa in supported:
        out = run_python("from vastray import native; print(native.isa())", isa=isa)
        assert out.returncode == 0, out.stderr
        assert out.stdout.strip() == isa
    bad = run_python(
        "from vastray import native\ntry:\n    native.isa()\nexcept ValueError as e:\n    print('error:', e)",
        isa="avx1024",
    )
    assert "error: VASTRAY_ISA must be one of sse2, avx, avx2, avx512 (got 'avx1024')" in bad.stdout, (
        bad.stdout + bad.stderr
    )


_FRAMES = (
    DIGEST_SCRIPT
    + r"""
path = sys.argv[1]
out = {"isa": native.isa()}
with ModelFile(path) as f:
    scene = f.to_scene()
with OutOfCoreModel(path, make_cache(64 << 20)) as model:
    overview = frame_bounds(*model.bounds, width=96, height=64)
    e, t = np.asarray(overview.eye), np.asarray(overview.target)
    close = Camera(eye=tuple(t + (e - t) * 0.3), target=overview.target, width=96, height=64)
    parallel = frame_bounds(*model.bounds, width=96, height=64, projection="orthographic")
    cameras = {"overview": overview, "close": close, "orthographic": parallel}
    out.update(frame_digests(scene, model, cameras, (1, 4, 16), 6))
    origins, directions = overview.primary_rays()
    hits = scene.intersect(origins, directions)
    ok = hits["prim"] >= 0
    points = origins[ok] + directions[ok] * hits["t"][ok][:, None]
    rng = np.random.default_rng(5)
    ao_o = np.repeat(points + hits["normal"][ok] * 1e-3, 8, axis=0)
    ao_d = rng.normal(size=(len(ao_o), 3))
    out["intersect"] = digest(hits["t"], hits["prim"], hits["u"], hits["v"])
    out["occluded"] = digest(scene.occluded(ao_o, ao_d, 0.0, 5.0))
    picked = model.pick(origins[::7], directions[::7])
    out["pick"] = digest(picked.t, picked.prim)
print(json.dumps(out))
"""
)


def test_every_path_renders_identical_frames(plant_model: Path) -> None:
    results = {}
    for isa in native.supported_isas():
        out = run_python(_FRAMES, str(plant_model), isa=isa)
        assert out.returncode == 0, out.stderr[-3000:]
        results[isa] = json.loads(out.stdout)
        assert results[isa].pop("isa") == isa
    first, *others = results
    for isa in others:
        differ = [k for k, v in results[first].items() if results[isa][k] != v]
        assert not differ, f"{isa} differs from {first} in {differ}"


@pytest.mark.slow
@pytest.mark.parametrize("isa", [i for i in native.supported_isas() if i != native.isa()])
def test_renderer_tests_pass_on_every_path(isa: str) -> None:
    """The renderer's own tests, again on each path that is not the default one."""
    env = dict(os.environ, VASTRAY_ISA=isa)
    tests = [
        "tests/test_render.py",
        "tests/test_extremes.py",
        "tests/test_watertight.py",
        "tests/test_orthographic.py",
    ]
    result = subprocess.run(
        [sys.executable, "-m", "pytest", "-q", "-x", "-p", "no:cacheprovider", *tests],
        cwd=REPO, capture_output=True, text=True, env=env, timeout=1200,
    )  # fmt: skip
    assert result.returncode == 0, result.stdout[-4000:] + result.stderr[-2000:]


# ---- packets against single rays ------------------------------------------------------------


def views_of(path: Path, width: int = 160, height: int = 96) -> list[Camera]:
    with ModelFile(path) as f:
        lo, hi = (np.asarray(v) for v in f.bounds)
    overview = frame_bounds(lo, hi, width=width, height=height)
    e, t = np.asarray(overview.eye), np.asarray(overview.target)
    return [
        overview,
        Camera(eye=tuple(t + (e - t) * 0.25), target=overview.target, width=width, height=height),
    ]


@pytest.mark.parametrize("shading", ["sun", "ao", "indirect"])
def test_secondary_packets_give_single_ray_answers(plant_model: Path, shading: str) -> None:
    with ModelFile(plant_model) as f:
        scene = f.to_scene()
    with OutOfCoreModel(plant_model, make_cache(64 << 20)) as model:
        for camera in views_of(plant_model):
            kw = dict(shading=shading, ao_samples=12)
            single = render_camera(scene, camera, packets=1, **kw)
            for packets in (4, 16):
                frame = render_camera(scene, camera, packets=packets, **kw)
                np.testing.assert_array_equal(frame.image, single.image)
            for poe in (0.0, 2.0):
                single = model.render_complete(camera, pixels_of_error=poe, packets=1, **kw)
                for packets in (4, 16):
                    frame = model.render_complete(camera, pixels_of_error=poe, packets=packets, **kw)
                    np.testing.assert_array_equal(frame.image, single.image)
                    np.testing.assert_array_equal(frame.prim, single.prim)
                    assert frame.stats.secondary_rays == single.stats.secondary_rays


def test_batch_occlusion_packs_rays_without_changing_answers(
    plant_model: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """On the kd-tree (VASTRAY_ANYHIT=kd), rays from one origin go as packets; the same
    rays with their runs broken up (so every ray goes alone) give the same answers, and so
    do the packets when several are in flight at once (as on a large tree;
    VASTRAY_INTERLEAVE_BYTES=0 makes every tree one)."""
    monkeypatch.setenv("VASTRAY_ANYHIT", "kd")
    with ModelFile(plant_model) as f:
        scene = f.to_scene()
    camera = views_of(plant_model)[1]
    origins, directions = camera.primary_rays()
    hits = scene.intersect(origins, directions)
    ok = hits["prim"] >= 0
    assert ok.mean() > 0.3
    points = origins[ok] + directions[ok] * hits["t"][ok][:, None]
    normals = (
        hits["normal"][ok] * np.sign(-np.einsum("ij,ij->i", hits["normal"][ok], directions[ok]))[:, None]
    )
    rng = np.random.default_rng(1)
    o = np.repeat(points + normals * 1e-4, 8, axis=0)
    d = rng.normal(size=(len(o), 3))
    d[::5] = np.repeat(normals, 8, axis=0)[::5]  # some rays straight up from the surface
    d[::11, 1] = 0.0  # zero components
    tmax = rng.uniform(0.01, 20.0, size=len(o))
    packed = scene.occluded(o, d, 0.0, tmax)
    order = rng.permutation(len(o))
    alone = np.empty_like(packed)
    alone[order] = scene.occluded(o[order], d[order], 0.0, tmax[order])
    assert 0.05 < packed.mean() < 0.95
    np.testing.assert_array_equal(packed, alone)
    monkeypatch.setenv("VASTRAY_INTERLEAVE_BYTES", "0")
    np.testing.assert_array_equal(scene.occluded(o, d, 0.0, tmax), packed)
    in_flight = np.empty_like(packed)
    in_flight[order] = scene.occluded(o[order], d[order], 0.0, tmax[order])
    np.testing.assert_array_equal(in_flight, packed)


# ---- indirect light ---------------------------------------------------------------------------


def test_indirect_is_deterministic_and_the_same_out_of_core(plant_model: Path) -> None:
    with ModelFile(plant_model) as f:
        scene = f.to_scene()
    camera = views_of(plant_model)[1]
    a = render_camera(scene, camera, shading="indirect")
    b = render_camera(scene, camera, shading="indirect", threads=1, tile_size=8)
    np.testing.assert_array_equal(a.image, b.image)
    assert a.stats.secondary_rays >= 3 * (a.prim >= 0).sum()  # two diffuse rays and a shadow ray a pixel
    with OutOfCoreModel(plant_model, make_cache(64 << 20)) as model:
        full = model.render_complete(camera, shading="indirect", pixels_of_error=0.0)
    np.testing.assert_array_equal(full.prim, a.prim)
    np.testing.assert_array_equal(full.image, a.image)


def reference_filter(
    light: np.ndarray, depth: np.ndarray, normal: np.ndarray, pixel_angle: float
) -> np.ndarray:
    """The indirect mode's edge-aware filter written again in numpy, in double precision:
    three a-trous rounds (steps 1, 2, 4) of the 5-tap B3 kernel, each along x then y, each
    tap weighted by cos^16 of the normals' angle and 1 / (1 + dz^2), dz the depth step over
    a tolerance of depth * (2 * pixel_angle * offset + 1 %); taps outside the image or on
    pixels that hit nothing weigh 0, and pixels that hit nothing keep their light."""
    h, w = depth.shape
    hit = np.isfinite(depth)
    kernel = (3 / 8, 1 / 4, 1 / 16)

    def shifted(a: np.ndarray, offset: int, axis: int, fill: float) -> np.ndarray:
        out = np.full_like(a, fill)
        n = a.shape[axis]
        if abs(offset) < n:
            src = [slice(None)] * a.ndim
            dst = [slice(None)] * a.ndim
            src[axis] = slice(max(offset, 0), n + min(offset, 0))
            dst[axis] = slice(max(-offset, 0), n - max(offset, 0))
            out[tuple(dst)] = a[tuple(src)]
        return out

    z = depth.astype(np.float64)
    nrm = normal.astype(np.float64)
    cur = light.astype(np.float64)
    for step in (1, 2, 4):
        for axis in (1, 0):  # along x, then along y
            total = kernel[0] * cur
            weight = np.full((h, w), kernel[0])
            for t in (-2, -1, 1, 2):
                offset = t * step
                zq = shifted(z, offset, axis, np.inf)
                nq = shifted(nrm, offset, axis, 0.0)
                with np.errstate(invalid="ignore", divide="ignore"):
                    cosine = np.clip((nrm * nq).sum(axis=2), 0.0, None) ** 16
                    dz = (z - zq) / (z * (2 * pixel_angle * abs(offset) + 0.01))
                    wq = np.where(np.isfinite(zq) & hit, kernel[abs(t)] * cosine / (1 + dz * dz), 0.0)
                total += wq[..., None] * shifted(cur, offset, axis, 0.0)
                weight += wq
            cur = np.where(hit[..., None], total / weight[..., None], cur)
    return cur


def test_the_edge_aware_filter_matches_a_reference() -> None:
    """The filter of the indirect mode (`native.denoise_light`, on the running ISA path)
    against reference_filter above: two surfaces meeting at a depth step and a crease,
    holes and background, hit pixels at both ends of rows. It smooths the noise on each
    surface without mixing the two, and leaves pixels that hit nothing as they were."""
    h, w = 41, 57
    rng = np.random.default_rng(12)
    y, x = np.mgrid[0:h, 0:w]
    near = x < 30  # a near surface facing the eye, a far one tilted
    depth = np.where(near, 10.0 + 0.01 * y, 14.0 + 0.05 * x).astype(np.float32)
    depth[(x - 40) ** 2 + (y - 20) ** 2 < 25] = np.inf  # a hole
    depth[:3] = np.inf  # rows with nothing
    depth[5, 10:20] = np.inf
    tilt = np.array([0.6, 0.0, 0.8])
    normal = np.where(near[..., None], [0.0, 0.0, 1.0], tilt).astype(np.float32)
    base = np.where(near[..., None], [0.2, 0.4, 0.6], [0.7, 0.5, 0.1])
    light = (base * rng.uniform(0.0, 2.0, size=(h, w, 3))).astype(np.float32)
    angle = 0.002
    filtered = native.denoise_light(light, depth, normal, angle)
    assert filtered.dtype == np.float32 and filtered.shape == light.shape
    np.testing.assert_allclose(filtered, reference_filter(light, depth, normal, angle), rtol=1e-5, atol=1e-6)
    background = ~np.isfinite(depth)
    np.testing.assert_array_equal(filtered[background], light[background])
    for surface, colour in ((near, [0.2, 0.4, 0.6]), (~near, [0.7, 0.5, 0.1])):
        inside = surface & ~background
        # Less noise than before, around the surface's own colour: no light from the other.
        assert (filtered[inside].std(axis=0) < 0.5 * light[inside].std(axis=0)).all()
        np.testing.assert_allclose(filtered[inside].mean(axis=0), colour, rtol=0.1)
    with pytest.raises(ValueError, match="light and normal must be"):
        native.denoise_light(light[:, :-1], depth, normal, angle)
    with pytest.raises(ValueError, match="pixel_angle"):
        native.denoise_light(light, depth, normal, 0.0)


def slab_scene(albedo: int) -> native.Scene:
    mesh = trimesh.creation.box(extents=(40.0, 0.2, 40.0))  # y up: a thin floor, open sky above
    faces = np.asarray(mesh.faces, dtype=np.uint32)
    colours = np.full((len(faces), 3), albedo, dtype=np.uint8)
    return native.Scene(np.asarray(mesh.vertices, dtype=np.float64), faces, colours)


def test_open_floor_under_the_sky_shows_albedo_times_sky() -> None:
    scene = slab_scene(200)
    kw = dict(width=64, height=48)
    # The sun on the far side of the slab: the top sees the sky alone, the bottom nothing.
    top = render_camera(
        scene,
        Camera(eye=(0.0, 6.0, 9.0), target=(0.0, 0.0, 0.0), **kw),
        shading="indirect",
        sun_direction=[0.0, -1.0, 0.0],
    )
    seen = top.prim >= 0
    assert seen.mean() > 0.5
    sky = np.array([0.36, 0.39, 0.44])  # shading::kSky
    expected = np.clip(np.round(200 / 255 * sky * 255), 0, 255)
    assert np.abs(top.image[seen].astype(int) - expected).max() <= 1
    below = render_camera(
        scene,
        Camera(eye=(0.0, -6.0, 9.0), target=(0.0, 0.0, 0.0), **kw),
        shading="indirect",
        sun_direction=[0.0, 1.0, 0.0],
    )
    assert (below.prim >= 0).mean() > 0.5
    assert below.image[below.prim >= 0].max() == 0  # facing the ground: no sky, no sun, no bounce


def test_passes_draw_other_samples_and_averages_converge(plant_model: Path) -> None:
    with ModelFile(plant_model) as f:
        scene = f.to_scene()
    camera = views_of(plant_model, 128, 80)[1]
    passes = [render_camera(scene, camera, shading="indirect", sample_index=k) for k in range(24)]
    assert not np.array_equal(passes[0].image, passes[1].image)
    for p in passes[1:]:
        np.testing.assert_array_equal(p.prim, passes[0].prim)
        np.testing.assert_array_equal(p.depth, passes[0].depth)
    reference = average_passes([p.image for p in passes[8:]]).astype(np.float64)
    seen = passes[0].prim >= 0

    def error(images: list[np.ndarray]) -> float:
        return float(np.abs(average_passes(images).astype(np.float64) - reference)[seen].mean())

    one, four = error([passes[0].image]), error([p.image for p in passes[:4]])
    assert four < 0.75 * one, (one, four)
    ao = [render_camera(scene, camera, shading="ao", ao_samples=4, sample_index=k).image for k in range(2)]
    assert not np.array_equal(ao[0], ao[1])


def test_new_parameters_are_checked() -> None:
    params = native.RenderParams()
    assert params.sample_index == 0 and params.request_limit == 0
    assert "indirect" in native.SHADING_MODES
    params.shading = "indirect"
    assert params.shading == "indirect"
    for field, value in (("sample_index", -1), ("request_limit", -5)):
        bad = native.RenderParams()
        setattr(bad, field, value)
        with pytest.raises(ValueError, match=field):
            bad.validate()


# ---- loading ------------------------------------------------------------------------------------


def test_request_limit_raises_the_per_frame_bound(plant_model: Path) -> None:
    """A frame may queue request_limit blocks instead of the cache's per-frame bound; a
    full-detail render raises it, so it completes in fewer frames."""
    camera = views_of(plant_model)[0]
    frames, queued = {}, {}
    for limit in (4, 0):
        cache = native.BlockCache(32 << 20, 1, "count", 4, 256)  # 4 requests a frame by default
        with OutOfCoreModel(plant_model, cache, preload_levels=1) as model:
            first = model.render(camera, request_limit=limit)
            queued[limit] = first.stats.pending
            done = model.render_complete(camera, pixels_of_error=0.0, request_limit=limit)
            assert done.complete
            frames[limit] = done.frames
    assert queued[4] <= 4
    assert frames[0] < frames[4], frames
