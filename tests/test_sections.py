"""Section planes in the ray tracer, in core and out of core: rays see only the kept
side; where a ray enters a cut solid through a plane it sees the cap (a distinct shade,
at the plane's depth); cut geometry casts no shadow; picks see what frames see; the
out-of-core renderer at full detail gives exactly the in-core frames. Expected images
come from the analytic geometry of a box, not from the renderer."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from vastray import native
from vastray.build import BuildOptions, build_model
from vastray.camera import Camera
from vastray.outofcore import OutOfCoreModel, make_cache
from vastray.render import SceneRenderer, load_model
from vastray.renderer import PRIM_BACKGROUND, render_params

PRIM_CAP = -3
# The unit box, outward-facing triangles (so a ray inside it meets back faces).
BOX_VERTICES = np.array([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)], dtype=np.float64)
BOX_FACES = np.array(
    [
        [0, 1, 3],
        [0, 3, 2],  # x = 0
        [4, 6, 7],
        [4, 7, 5],  # x = 1
        [0, 4, 5],
        [0, 5, 1],  # y = 0
        [2, 3, 7],
        [2, 7, 6],  # y = 1
        [0, 2, 6],
        [0, 6, 4],  # z = 0
        [1, 5, 7],
        [1, 7, 3],  # z = 1
    ],
    dtype=np.uint32,
)
KEEP_RIGHT = (1.0, 0.0, 0.0, -0.5)  # keeps x >= 0.5
KEEP_LEFT = (-1.0, 0.0, 0.0, 0.5)  # keeps x <= 0.5


def box(offset: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> SceneRenderer:
    scene = native.Scene(BOX_VERTICES + np.array(offset), BOX_FACES)
    return SceneRenderer(scene, "box")


def looking_along_x(offset: tuple[float, float, float] = (0.0, 0.0, 0.0), size: int = 64) -> Camera:
    o = np.array(offset)
    return Camera(
        eye=tuple(o + np.array([-2.0, 0.5, 0.5])),
        target=tuple(o + np.array([0.5, 0.5, 0.5])),
        up=(0.0, 0.0, 1.0),
        fov=40.0,
        width=size,
        height=size,
    )


def shifted(
    plane: tuple[float, float, float, float], offset: tuple[float, float, float]
) -> tuple[float, ...]:
    n = np.array(plane[:3])
    return (*plane[:3], plane[3] - float(n @ np.array(offset)))


@pytest.mark.parametrize("offset", [(0.0, 0.0, 0.0), (3e6, -1e6, 2e6)], ids=["origin", "far"])
def test_a_cut_box_shows_its_cap_at_the_plane(offset: tuple[float, float, float]) -> None:
    model, camera = box(offset), looking_along_x(offset)
    origins, directions = camera.primary_rays()
    # Where each pixel's ray crosses the plane x = 0.5 (relative to the box), and whether
    # that point is inside the box's cross-section (away from its edges).
    t_plane = (offset[0] + 0.5 - origins[:, 0]) / directions[:, 0]
    at = origins + directions * t_plane[:, None] - np.array(offset)
    inside = (np.abs(at[:, 1] - 0.5) < 0.48) & (np.abs(at[:, 2] - 0.5) < 0.48)
    outside = (np.abs(at[:, 1] - 0.5) > 0.52) | (np.abs(at[:, 2] - 0.5) > 0.52)
    assert inside.sum() > 500 and outside.sum() > 500

    plain = model.render(camera, shading="headlight")
    cut = model.render(camera, shading="headlight", sections=[shifted(KEEP_RIGHT, offset)])
    prim, depth = cut.prim.ravel(), cut.depth.ravel()
    assert (prim[inside] == PRIM_CAP).all(), "rays into the cut box must see its cap"
    np.testing.assert_allclose(depth[inside], t_plane[inside], rtol=1e-5)
    assert (prim[outside] == PRIM_BACKGROUND).all()  # beside the box: nothing on the kept side ahead

    # A cap has its own hue (lit from the eye), unlike any face of the uncut box.
    def hue(rgb: np.ndarray) -> np.ndarray:
        rgb = rgb.astype(np.float64)
        return rgb / rgb.sum(axis=1, keepdims=True)

    caps = hue(cut.image.reshape(-1, 3)[inside])
    faces = hue(plain.image.reshape(-1, 3)[plain.prim.ravel() >= 0])
    assert np.ptp(caps, axis=0).max() < 0.02
    assert np.abs(faces - caps.mean(axis=0)).max(axis=1).min() > 0.1
    # Keeping the near half instead: the front face is seen as before, no caps.
    near = model.render(camera, shading="headlight", sections=[shifted(KEEP_LEFT, offset)])
    np.testing.assert_array_equal(near.prim, plain.prim)
    np.testing.assert_array_equal(near.depth, plain.depth)
    # Cut everything away: nothing is seen.
    gone = model.render(camera, sections=[shifted(KEEP_RIGHT, offset), (0.0, 1.0, 0.0, -1e7)])
    assert (gone.prim == PRIM_BACKGROUND).all()


def test_cut_geometry_casts_no_shadow() -> None:
    """A roof over a floor, the sun low from one side: the roof's shadow falls on the
    floor beside it. Cut the roof away with a plane and the floor is evenly lit."""
    floor = np.array([[-3, 0, -3], [3, 0, -3], [3, 0, 3], [-3, 0, 3]], dtype=np.float64)
    roof = floor * [0.3, 0, 0.3] + [0, 1, 0]
    vertices = np.vstack([floor, roof])
    faces = np.array([[0, 2, 1], [0, 3, 2], [4, 6, 5], [4, 7, 6]], dtype=np.uint32)
    model = SceneRenderer(native.Scene(vertices, faces), "roof")
    camera = Camera(
        eye=(0.0, 8.0, 0.01), target=(0.0, 0.0, 0.0), up=(0.0, 0.0, 1.0), fov=45.0, width=64, height=64
    )
    sun = {"shading": "sun", "sun_direction": (1.0, 1.0, 0.0)}
    with_roof = model.render(camera, **sun)
    floor_seen = with_roof.prim.ravel() <= 1
    floor_seen &= with_roof.prim.ravel() >= 0
    grey = with_roof.image.reshape(-1, 3).astype(int).sum(axis=1)
    assert np.ptp(grey[floor_seen]) > 100, "the roof should shade part of the floor"
    # Keep y <= 0.5: the roof at y = 1 is cut away, and with it its shadow.
    cut = model.render(camera, sections=[(0.0, -1.0, 0.0, 0.5)], **sun)
    floor_now = cut.prim.ravel() >= 0
    assert floor_now.mean() > 0.5 and set(np.unique(cut.prim[cut.prim >= 0])) <= {0, 1}
    grey_now = cut.image.reshape(-1, 3).astype(int).sum(axis=1)
    assert np.ptp(grey_now[floor_now]) <= 3


def test_picks_see_what_frames_see() -> None:
    model = box()
    origins = np.array([[-2.0, 0.4, 0.6], [-2.0, 0.5, 0.5], [0.2, 5.0, 0.5]])
    directions = np.array([[1.0, 0.0, 0.0], [1.0, 0.05, 0.0], [0.0, -1.0, 0.0]])
    plain = model.pick(origins, directions)
    np.testing.assert_allclose(plain.position[0], [0.0, 0.4, 0.6], atol=1e-6)  # the front face
    cut = model.pick(origins, directions, sections=[KEEP_RIGHT])
    # Through the cut box: its cap, on the plane, facing the eye.
    np.testing.assert_allclose(cut.position[0], [0.5, 0.4, 0.6], atol=1e-6)
    np.testing.assert_allclose(cut.normal[0], [-1.0, 0.0, 0.0], atol=1e-6)
    assert math.isclose(cut.t[0], 2.5, rel_tol=1e-6) and cut.prim[0] >= 0
    assert cut.prim[1] >= 0 and 0.5 - 1e-6 <= cut.position[1][0]
    # A ray that stays on the cut side sees nothing.
    assert cut.prim[2] == -1 and plain.prim[2] >= 0


@pytest.mark.parametrize("projection", ["perspective", "orthographic"])
def test_full_detail_out_of_core_equals_in_core_with_sections(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, projection: str
) -> None:
    # The out-of-core walk is the kd-tree's, so its in-core twin is the reference: the wide
    # BVH's primary rays may take the other of two triangles hit at the same float t (on
    # this view two coincident triangles facing opposite ways, the lower index facing away:
    # a cap where the kd walk shows the other's face).
    monkeypatch.setenv("VASTRAY_PRIMARY", "kd")
    source = "scene:plant:20000:3"
    incore = load_model(source)
    path = tmp_path / "plant.vast"
    build_model(source, path, BuildOptions(memory=64 << 20))
    decoded = load_model(str(path))
    lo, hi = (np.array(b) for b in incore.bounds)
    centre = (lo + hi) / 2
    planes = [(-1.0, 0.0, 0.0, float(centre[0])), (0.0, 0.0, 1.0, -float(centre[2] - 0.2 * (hi - lo)[2]))]
    eye = tuple(centre + (hi - lo) * [0.9, 0.6, 1.1])
    camera = Camera(eye=eye, target=tuple(centre), width=96, height=72, projection=projection)
    with OutOfCoreModel(path, make_cache(64 << 20)) as model:
        for shading in ("headlight", "sun", "ao"):
            params = render_params(shading=shading, pixels_of_error=0.0, ao_samples=4, sections=planes)
            ours = model.render_complete(camera, params)
            ref = decoded.render(camera, params)
            assert (ours.prim == PRIM_CAP).sum() > 0, "the planes cut through solids"
            np.testing.assert_array_equal(ours.prim, ref.prim)
            np.testing.assert_array_equal(ours.depth, ref.depth)
            np.testing.assert_array_equal(ours.image, ref.image)
        o, d = camera.image_rays(np.array([[48.5, 36.5], [10.5, 60.5], [80.5, 20.5]]))
        a = model.pick(o, d, sections=planes)
        b = decoded.pick(o, d, sections=planes)
        np.testing.assert_array_equal(a.prim, b.prim)
        np.testing.assert_allclose(a.position, b.position, rtol=0, atol=1e-4 * np.linalg.norm(hi - lo))


@pytest.mark.parametrize(
    ("interleave_from", "projection"),
    [("", "perspective"), ("0", "perspective"), ("", "orthographic")],
    ids=["one-at-a-time", "in-flight", "orthographic"],
)
def test_packets_give_the_single_rays_frames_with_sections(
    tmp_path: Path, interleave_from: str, projection: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Sectioned rays go in packets too: each lane keeps its own segment on the kept side,
    and a ray with nothing left enters no cell. 2x2 and 4x4 packets, one at a time or in
    flight (VASTRAY_INTERLEAVE_BYTES=0 forces it on a small model), give the single rays'
    frames bit for bit, in core and out of core, at full detail and with voxels, with caps,
    shadows and AO, and with planes that cut everything away."""
    monkeypatch.setenv("VASTRAY_INTERLEAVE_BYTES", interleave_from)
    source = "scene:plant:20000:3"
    incore = load_model(source)
    path = tmp_path / "plant.vast"
    build_model(source, path, BuildOptions(memory=64 << 20))
    lo, hi = (np.array(b) for b in incore.bounds)
    centre = (lo + hi) / 2
    cut = [(-1.0, 0.0, 0.0, float(centre[0])), (0.0, 0.0, 1.0, -float(centre[2] - 0.2 * (hi - lo)[2]))]
    everything = [(1.0, 0.0, 0.0, -float(hi[0]) - 1.0)]  # keeps x beyond the model
    eye = tuple(centre + (hi - lo) * [0.9, 0.6, 1.1])
    camera = Camera(eye=eye, target=tuple(centre), width=96, height=72, projection=projection)
    with OutOfCoreModel(path, make_cache(64 << 20)) as model:
        renderers = [
            ("in core", lambda **f: incore.render(camera, render_params(**f))),
            ("out of core", lambda **f: model.render_complete(camera, render_params(**f))),
        ]
        for name, render in renderers:
            for shading in ("headlight", "sun", "ao"):
                for poe in (0.0, 2.0) if name == "out of core" else (0.0,):
                    fields = {"shading": shading, "pixels_of_error": poe, "ao_samples": 4, "sections": cut}
                    single = render(packets=1, **fields)
                    assert (single.prim == PRIM_CAP).sum() > 0, "the planes cut through solids"
                    assert (single.prim >= 0).sum() > 0 and (single.prim == PRIM_BACKGROUND).sum() > 0
                    for packets in (4, 16):
                        frame = render(packets=packets, **fields)
                        what = f"{name}, {shading}, PoE {poe}, {packets} rays"
                        np.testing.assert_array_equal(frame.prim, single.prim, err_msg=what)
                        np.testing.assert_array_equal(frame.depth, single.depth)
                        np.testing.assert_array_equal(frame.image, single.image)
                        # Packets did walk: one step serves several rays.
                        assert frame.stats.node_visits < single.stats.node_visits, what
            for packets in (1, 4, 16):
                gone = render(packets=packets, sections=everything)
                assert (gone.prim == PRIM_BACKGROUND).all()


@pytest.mark.parametrize(
    ("planes", "message"),
    [
        ([(0.0, 0.0, 0.0, 1.0)], "non-zero normal"),
        ([(math.nan, 0.0, 1.0, 0.0)], "finite"),
        ([(1.0, 0.0, 0.0, math.inf)], "finite"),
        ([(1.0, 0.0, 0.0, 0.0)] * 7, "at most 6"),
    ],
)
def test_bad_planes_are_refused(planes: list[tuple[float, ...]], message: str) -> None:
    model = box()
    with pytest.raises(ValueError, match=message):
        model.render(looking_along_x(), sections=planes)
    with pytest.raises(ValueError, match=message):
        model.pick(np.zeros((1, 3)), np.ones((1, 3)), sections=planes)
