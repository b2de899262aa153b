"""Orthographic cameras: parallel rays along the view over the extent the perspective
view has at the target, starting behind the model. The frames of both renderers must
show what a double-precision brute force sees along those rays, keep sizes at every
depth, cut nothing off at the eye, agree with each other at full detail (single rays,
and packets, which take the walk ordered by the direction's signs), and pick their level
of detail by a pixel's width, which is the same at every depth."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
import trimesh
from PIL import Image
from test_build import run_cli
from views import render_camera

from vastray import native
from vastray.build import BuildOptions, build_model
from vastray.camera import Camera, frame_bounds
from vastray.modelfile import ModelFile
from vastray.outofcore import OutOfCoreModel, make_cache


def cube(centre: tuple[float, float, float], size: float) -> trimesh.Trimesh:
    box = trimesh.creation.box(extents=(size, size, size))
    box.apply_translation(centre)
    return box


def scene_of(*meshes: trimesh.Trimesh) -> tuple[native.Scene, np.ndarray, np.ndarray]:
    mesh = trimesh.util.concatenate(list(meshes))
    vertices = np.asarray(mesh.vertices, dtype=np.float64)
    faces = np.asarray(mesh.faces, dtype=np.uint32)
    return native.Scene(vertices, faces), vertices, faces


@pytest.fixture(scope="module")
def boxes() -> tuple[native.Scene, np.ndarray, np.ndarray]:
    """A floor, two cubes and a sphere: edges at every angle to an oblique view."""
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=0.6)
    sphere.apply_translation((0.8, 0.6, -0.7))
    floor = trimesh.creation.box(extents=(4.0, 0.1, 4.0))
    floor.apply_translation((0.0, -0.05, 0.0))
    return scene_of(floor, cube((-0.9, 0.5, 0.4), 1.0), cube((0.9, 0.3, 0.9), 0.6), sphere)


def ortho(camera: Camera) -> Camera:
    return dataclasses.replace(camera, projection="orthographic")


@pytest.mark.parametrize("walk", ["wide", "kd"])
def test_frames_see_what_a_brute_force_sees_along_parallel_rays(
    boxes: tuple, walk: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    """In core, through the wide BVH and the kd-tree, whose packets take rays from
    different origins when their directions' signs agree."""
    monkeypatch.setenv("VASTRAY_PRIMARY", walk)
    scene, vertices, faces = boxes
    camera = frame_bounds(
        *scene.bounds, width=160, height=120, direction=(0.8, 0.9, 1.1), projection="orthographic"
    )
    origins, directions = camera.primary_rays(scene.bounds)
    # Parallel rays from a plane behind the whole model.
    assert np.ptp(directions, axis=0).max() == 0.0 and np.ptp(origins, axis=0).max() > 0
    lo, hi = (np.asarray(b) for b in scene.bounds)
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    assert ((corners - origins[0]) @ directions[0] > 0).all()
    ref = native.reference_intersect(vertices, faces, origins, directions)
    for packets in (1, 4, 16):
        frame = render_camera(scene, camera, shading="normal", packets=packets)
        prim = frame.prim.ravel()
        assert 0.3 < (prim >= 0).mean() < 0.95
        same = (prim == ref["prim"]).mean()
        assert same >= 0.998, f"packets {packets}: only {same:.4%} of the pixels see the reference's triangle"
        both = (prim >= 0) & (prim == ref["prim"])
        np.testing.assert_allclose(frame.depth.ravel()[both], ref["t"][both], rtol=1e-5)
    # Python's rays are the renderer's: a batch query on them is the frame.
    hits = scene.intersect(origins, directions)
    np.testing.assert_array_equal(hits["prim"], frame.prim.ravel())


def test_sizes_stay_with_depth_and_the_eye_cuts_nothing_off() -> None:
    """Two equal cubes, one 10 units behind the other, side by side in a view along -z:
    orthographic, both cover the same pixels; in perspective the far one is smaller. With
    the eye between them, the orthographic view still shows both."""
    near, far = cube((-1.0, 0.0, 0.0), 1.0), cube((1.0, 0.0, -10.0), 1.0)
    scene, _, _ = scene_of(near, far)
    n_near = len(near.faces)
    camera = Camera(eye=(0.0, 0.0, 20.0), target=(0.0, 0.0, -5.0), fov=20.0, width=200, height=100)

    def areas(cam: Camera) -> tuple[int, int]:
        prim = render_camera(scene, cam, shading="normal").prim
        return int(((prim >= 0) & (prim < n_near)).sum()), int((prim >= n_near).sum())

    a_near, a_far = areas(ortho(camera))
    # A unit face over pixels of 2 * 25 tan(10 deg) / 100 units: about 129 pixels each.
    pixel = 2 * 25 * np.tan(np.radians(10.0)) / 100
    assert a_near == pytest.approx(1 / pixel**2, rel=0.1) and abs(a_near - a_far) <= 0.05 * a_near
    p_near, p_far = areas(camera)
    assert p_far < 0.75 * p_near
    inside = Camera(eye=(0.0, 0.0, -5.0), target=(0.0, 0.0, -30.0), fov=20.0, width=200, height=100)
    assert areas(ortho(inside)) == (a_near, a_far)  # the same extent: 25 units to the target
    seen_near, seen_far = areas(inside)
    assert seen_near == 0 and seen_far > 0  # perspective: the near cube is behind the eye


@pytest.fixture(scope="module")
def plant(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, native.Scene]:
    path = tmp_path_factory.mktemp("ortho") / "plant.vast"
    build_model("scene:plant:60000:3", path, BuildOptions())
    with ModelFile(path) as f:
        return path, f.to_scene()


@pytest.mark.parametrize("shading", ["headlight", "sun"])
def test_full_detail_out_of_core_equals_in_core(plant: tuple[Path, native.Scene], shading: str) -> None:
    """At PoE 0 an orthographic frame of the built model is the decoded scene's, pixel for
    pixel, oblique and along an axis (zero direction components), its packets walked in
    the order of the direction's signs; tiles outside the model's outline are background
    without a walk, as the batch query finds."""
    path, scene = plant
    with OutOfCoreModel(path, make_cache(1 << 30)) as model:
        for view in ("iso", "front", "top"):
            camera = frame_bounds(*model.bounds, width=128, height=96, view=view, projection="orthographic")
            expected = model.pick(*camera.primary_rays(model.bounds)).prim.reshape(
                camera.height, camera.width
            )
            assert 0.05 < (expected >= 0).mean() < 0.95
            for packets in (1, 4, 16):
                frame = model.render_complete(camera, shading=shading, pixels_of_error=0.0, packets=packets)
                ref = render_camera(scene, camera, shading=shading, packets=packets)
                assert frame.complete and frame.stats.voxel_hits == 0
                np.testing.assert_array_equal(frame.prim, ref.prim)
                np.testing.assert_array_equal(frame.depth, ref.depth)
                np.testing.assert_array_equal(frame.prim, expected)
                if shading == "headlight":
                    np.testing.assert_array_equal(frame.image, ref.image)
                assert frame.stats.primary_rays == camera.width * camera.height


def test_level_of_detail_follows_the_pixel_width_at_every_depth(plant: tuple[Path, native.Scene]) -> None:
    """Moving eye and target together along the view keeps an orthographic image (the
    same parallel rays, the same pixel width), and so its level of detail: the same
    voxels at PoE 4, though every voxel is twice as far from the eye. The same move
    coarsens a perspective view."""
    path, _ = plant
    with OutOfCoreModel(path, make_cache(1 << 30)) as model:
        base = frame_bounds(*model.bounds, width=160, height=120, projection="orthographic")
        eye, target = np.asarray(base.eye), np.asarray(base.target)
        back = dataclasses.replace(base, eye=tuple(eye + (eye - target)), target=tuple(eye))
        near, far = (model.render_complete(c, pixels_of_error=4.0) for c in (base, back))
        assert near.stats.voxel_hits > 0.05 * near.stats.primary_rays
        assert abs(near.stats.voxel_hits - far.stats.voxel_hits) <= 0.002 * near.stats.voxel_hits
        assert (near.prim != far.prim).mean() < 0.002
        near_p, far_p = (
            model.render_complete(dataclasses.replace(c, projection="perspective"), pixels_of_error=4.0)
            for c in (base, back)
        )
        voxel_share = [f.stats.voxel_hits / max(1, int((f.prim != -1).sum())) for f in (near_p, far_p)]
        assert voxel_share[1] > 1.2 * voxel_share[0]


# 27 unit cubes, centres 2 apart (faces at +-0.5, +-1.5, +-2.5), seen along the axes from
# eyes in their face planes: the middle row and column of rays (33 x 33 pixels) start
# exactly in planes the kd-tree splits at, with exactly zero direction components.
CUBE_VIEWS = {
    "front": ((0.5, 0.5, 10.0), (0.5, 0.5, 0.0), (0.0, 1.0, 0.0)),
    "along-x": ((-10.0, 1.5, -0.5), (0.0, 1.5, -0.5), (0.0, 0.0, 1.0)),
    "top": ((2.5, 10.0, -1.5), (2.5, 0.0, -1.5), (0.0, 0.0, -1.0)),
}


@pytest.mark.parametrize("quantized", [True, False])
@pytest.mark.parametrize("name", CUBE_VIEWS.keys())
def test_axis_views_of_cubes_with_exact_coordinates(tmp_path: Path, name: str, quantized: bool) -> None:
    """Packets of parallel rays with zero direction components (out of core) answer as
    single rays do and as the decoded scene does, at full detail and at PoE 2, rays in
    split planes included (the planes at the faces themselves where splits are not
    quantized); the hits are the brute force's."""
    cubes = [
        trimesh.creation.box(extents=(1.0, 1.0, 1.0), transform=trimesh.transformations.translation_matrix(c))
        for c in np.array(np.meshgrid(*[(-2.0, 0.0, 2.0)] * 3)).reshape(3, -1).T
    ]
    mesh = trimesh.util.concatenate(cubes)
    mesh.export(tmp_path / "cubes.ply")
    path = tmp_path / "cubes.vast"
    build_model(str(tmp_path / "cubes.ply"), path, BuildOptions(quantized_splits=quantized))
    with ModelFile(path) as f:
        scene = f.to_scene()
    assert scene.build_stats["nodes"] > 50  # split planes at the faces
    eye, target, up = CUBE_VIEWS[name]
    camera = Camera(eye, target, up, 40.0, 33, 33, "orthographic")
    origins, directions = camera.primary_rays(scene.bounds)
    assert (directions == 0).sum() == 2 * 33 * 33  # two zero components in every ray
    vertices, faces = np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces, dtype=np.uint32)
    ref = native.reference_intersect(vertices, faces, origins, directions)
    with OutOfCoreModel(path, make_cache(64 << 20)) as model:
        for poe in (0.0, 2.0):
            single = model.render_complete(camera, pixels_of_error=poe, packets=1)
            for packets in (4, 16):
                frame = model.render_complete(camera, pixels_of_error=poe, packets=packets)
                np.testing.assert_array_equal(frame.prim, single.prim)
                np.testing.assert_array_equal(frame.depth, single.depth)
        full = model.render_complete(camera, pixels_of_error=0.0, packets=16)
    decoded = render_camera(scene, camera, packets=16)
    np.testing.assert_array_equal(full.prim, decoded.prim)
    np.testing.assert_array_equal(full.depth, decoded.depth)
    hit = ref["prim"] >= 0
    assert 0.1 < hit.mean() < 0.9
    assert (full.prim.ravel()[hit] >= 0).all()
    np.testing.assert_allclose(full.depth.ravel()[hit], ref["t"][hit], rtol=1e-6)


def test_the_cli_renders_orthographic_views(plant: tuple[Path, native.Scene], tmp_path: Path) -> None:
    """`vastray render --projection orthographic` writes the frame the Python API gives
    for that camera, and prints the camera with its projection, to repeat it."""
    path, _ = plant
    out = run_cli("render", str(path), "-o", "o.png", "--size", "96x64", "--projection", "orthographic",
                  "--view", "front", cwd=tmp_path)  # fmt: skip
    assert out.returncode == 0, out.stderr
    assert "--projection orthographic" in out.stdout
    shown = np.asarray(Image.open(tmp_path / "o.png").convert("RGB"))
    with OutOfCoreModel(path, make_cache(1 << 30)) as model:
        camera = frame_bounds(*model.bounds, width=96, height=64, view="front", projection="orthographic")
        frame = model.render_complete(camera, pixels_of_error=0.0)
        perspective = model.render_complete(dataclasses.replace(camera, projection="perspective"))
    np.testing.assert_array_equal(shown, frame.image)
    assert (perspective.prim != frame.prim).mean() > 0.1
    bad = run_cli("render", str(path), "-o", "x.png", "--projection", "isometric", cwd=tmp_path)
    assert bad.returncode == 2 and "invalid choice: 'isometric'" in bad.stderr


def test_bad_projection_is_refused() -> None:
    with pytest.raises(ValueError, match="projection must be one of perspective, orthographic"):
        Camera(eye=(0, 0, 5), target=(0, 0, 0), projection="isometric").validate()
    with pytest.raises(ValueError, match="projection"):
        frame_bounds((0, 0, 0), (1, 1, 1), projection="fisheye")
