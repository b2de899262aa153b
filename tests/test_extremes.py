"""Numerical stability at the extremes, and bad input.

* Axis-parallel rays whose other direction components are +0 or -0, including rays
  exactly through vertices and rays lying in the bounding box's faces: no NaN in any
  output, hits agree with the double reference (rules of `compare_with_reference`).
* Models translated by 1e6 and 1e7 and scaled by 1e-4 and 1e4 agree with the
  reference within a tolerance scaled to the coordinate magnitude. Per ray, in distance
  along the ray: ``|t - t_ref| * |d| <= 1e-5 * max(t_ref * |d|, L) + 8 eps32 L / |cos θ|
  + 16 eps64 |offset|``, L the model's diagonal. The first two terms are the untranslated
  bound (float32 geometry stored relative to the model's centre has an absolute error of
  a few eps32 * L whatever the translation, grazing rays magnify it by 1/|cos θ|). The
  last term is the double rounding of world coordinates: translated vertices and ray
  origins are themselves rounded to ulp(|offset|) = eps64 |offset| before either
  intersector sees them, and both subtract them in double. The test fails if the core
  loses the centre-relative precision: at 1e7 a float32 world coordinate is off by ~0.5,
  far above 1e-5 L for a model of size 0.2 (the bunny).
* Zero-area triangles (a point, two equal corners, three collinear corners, with
  exactly representable coordinates so they stay degenerate in float) are never hit.
* Camera inside a closed model: every pixel hits, at a finite positive depth.
* Shadow rays on a finely tessellated sphere never shadow the lit side (a convex body
  cannot shadow itself).
* Empty batches, NaN/zero/infinite rays, tmin/tmax, and ValueError with a clear message
  for bad scenes, bad cameras and unknown shading modes.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import pytest
import trimesh
from views import render_view

from vastray import native

if TYPE_CHECKING:
    from conftest import Agreement, ModelMesh

F32_EPS = float(np.finfo(np.float32).eps)
F64_EPS = float(np.finfo(np.float64).eps)


def assert_agrees(a: Agreement, label: str, max_graze_fraction: float = 1e-4) -> None:
    print(f"{label}: {a.summary()}")
    assert a.nonfinite == 0, f"{label}: NaN or inconsistent outputs"
    assert len(a.bad_mismatches) == 0, f"{label}: hit/miss differs, rays {a.bad_mismatches[:10]}"
    assert a.graze_mismatches <= max_graze_fraction * a.rays, label
    assert len(a.bad_t) == 0, f"{label}: t outside tolerance, rays {a.bad_t[:10]}"
    assert len(a.bad_prims) == 0, f"{label}: wrong triangle, rays {a.bad_prims[:10]}"
    assert a.max_point_error <= 1.0, label


# ---------------------------------------------------------------------------------------
# Axis-parallel rays with signed zeros


def axis_rays(
    vertices: np.ndarray, faces: np.ndarray, n: int, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rays along ±x, ±y, ±z whose two other components are +0 or -0 at random. Their
    other two origin coordinates are random in the box, or copied from a vertex (the ray
    then passes exactly through it), or on the box's faces (the ray lies in a face of the
    root cell, and in the model's own face where that is planar). Along their axis they
    start before the box, inside it (not the rays through vertices: those would start on
    the surface) or far away. Returns origins, directions, and which of the three kinds."""
    used = vertices[np.unique(faces)]
    lo, hi = used.min(axis=0), used.max(axis=0)
    diag = float(np.linalg.norm(hi - lo))
    axis = rng.integers(0, 3, n)
    sign = np.where(rng.random(n) < 0.5, -1.0, 1.0)
    directions = np.where(rng.random((n, 3)) < 0.5, 0.0, -0.0)
    rows = np.arange(n)
    directions[rows, axis] = sign * rng.uniform(0.01, 100.0, n)

    origins = lo + rng.random((n, 3)) * (hi - lo)
    kind = rng.integers(0, 3, n)
    at_vertex = kind == 1
    origins[at_vertex] = used[rng.integers(0, len(used), int(at_vertex.sum()))]
    on_face = kind == 2
    face_axis = (axis[on_face] + rng.integers(1, 3, int(on_face.sum()))) % 3
    origins[np.flatnonzero(on_face), face_axis] = np.where(
        rng.random(int(on_face.sum())) < 0.5, lo[face_axis], hi[face_axis]
    )
    start = rng.integers(0, 3, n)
    start[at_vertex & (start == 1)] = 0
    along = np.where(sign > 0, lo[axis], hi[axis]) - sign * np.where(start == 0, 0.25, 1e3) * diag
    outside = start != 1
    origins[rows[outside], axis[outside]] = along[outside]
    return origins, directions, kind


def test_axis_parallel_rays_with_signed_zeros(
    model_path: Path,
    load_model: Callable[[Path], ModelMesh],
    reference_check: Callable[..., Agreement],
) -> None:
    """Rays exactly through vertices, or lying in a planar face of the model, touch
    edges exactly; there either intersector may fairly see or round away the contact
    (the double reference is not watertight), so their grazing disagreements are
    reported and bounded loosely; the rays from random points meet the usual 1e-4 bar."""
    mesh = load_model(model_path)
    scene = native.Scene(mesh.vertices, mesh.faces)
    origins, directions, kind = axis_rays(mesh.vertices, mesh.faces, 30_000, np.random.default_rng(5))
    zero = directions == 0
    assert np.signbit(directions[zero]).any() and not np.signbit(directions[zero]).all()
    groups = (
        ("random", kind == 0, 1e-4, 0.1),
        ("through vertices", kind == 1, 0.05, 0.9),
        ("in box faces", kind == 2, 0.05, 0.0),
    )
    for label, rows, graze, min_hits in groups:
        a = reference_check(
            scene, mesh.vertices, mesh.faces, origins[rows], directions[rows], length=mesh.diagonal
        )
        assert_agrees(a, f"{mesh.name} {label}", max_graze_fraction=graze)
        assert a.hits >= min_hits * a.rays
    hits = scene.intersect(origins, directions)
    for key in ("t", "u", "v"):
        assert not np.isnan(hits[key]).any(), key
    np.testing.assert_array_equal(scene.occluded(origins, directions), hits["prim"] >= 0)


def test_axis_rays_on_a_box_with_exact_coordinates() -> None:
    """A unit cube: axis rays through its corners, edges and faces from every side, with
    every combination of signed zeros, hit at exactly known distances."""
    box = trimesh.creation.box(extents=(2.0, 2.0, 2.0))
    scene = native.Scene(np.asarray(box.vertices, dtype=np.float64), np.asarray(box.faces, dtype=np.uint32))
    coords = np.array([-1.0, -0.5, 0.0, 0.25, 1.0])  # corners, face interiors, edges
    origins, directions, expected = [], [], []
    for axis in range(3):
        others = [k for k in range(3) if k != axis]
        for a in coords:
            for b in coords:
                for sign in (-1.0, 1.0):
                    for z0, z1 in ((0.0, 0.0), (0.0, -0.0), (-0.0, 0.0), (-0.0, -0.0)):
                        o = np.zeros(3)
                        o[others[0]], o[others[1]] = a, b
                        o[axis] = -3.0 * sign
                        d = np.zeros(3)
                        d[others[0]], d[others[1]] = z0, z1
                        d[axis] = sign * 0.5
                        origins.append(o)
                        directions.append(d)
                        expected.append(4.0)  # distance 2 to the face, |d| = 0.5
    o, d, t_expected = np.array(origins), np.array(directions), np.array(expected)
    hits = scene.intersect(o, d)
    assert (hits["prim"] >= 0).all(), "an axis ray through the cube's closed surface missed"
    np.testing.assert_allclose(hits["t"], t_expected, rtol=1e-6)
    assert np.isfinite(hits["u"]).all() and np.isfinite(hits["v"]).all()
    ref = native.reference_intersect(box.vertices, box.faces, o, d)
    np.testing.assert_allclose(ref["t"], t_expected, rtol=1e-12)


# ---------------------------------------------------------------------------------------
# Translated and scaled models


TRANSFORMS = {
    "offset-1e6": (1.0, 1e6),
    "offset-1e7": (1.0, 1e7),
    "scale-1e-4": (1e-4, 0.0),
    "scale-1e4": (1e4, 0.0),
}


@pytest.mark.parametrize("transform", TRANSFORMS.keys())
def test_translated_and_scaled_models(
    transform: str,
    load_model: Callable[[Path], ModelMesh],
    models_folder: Path,
    reference_check: Callable[..., Agreement],
) -> None:
    path = models_folder / "stanford-bunny.obj"
    if not path.exists():
        pytest.skip(f"{path} missing")
    mesh = load_model(path)
    scale, distance = TRANSFORMS[transform]
    offset = distance * np.array([0.6, -0.48, 0.64])  # |offset| = distance, all axes
    vertices = mesh.vertices * scale + offset
    used = vertices[np.unique(mesh.faces)]
    lo, hi = used.min(axis=0), used.max(axis=0)
    centre, diag = (lo + hi) / 2, float(np.linalg.norm(hi - lo))

    rng = np.random.default_rng(11)
    n = 40_000
    sphere = rng.normal(size=(n, 3))
    sphere /= np.linalg.norm(sphere, axis=1, keepdims=True)
    origins = centre + sphere * diag
    directions = lo + rng.random((n, 3)) * (hi - lo) - origins
    inner = slice(0, n // 5)
    origins[inner] = lo + rng.random((n // 5, 3)) * (hi - lo)

    scene = native.Scene(vertices, mesh.faces)
    np.testing.assert_allclose(scene.centre, centre, rtol=0, atol=4 * F64_EPS * distance + 1e-6 * diag)
    a = reference_check(
        scene,
        vertices,
        mesh.faces,
        origins,
        directions,
        length=diag,
        abs_distance=16 * F64_EPS * distance,
    )
    assert_agrees(a, transform)
    assert a.hits > 0.3 * n

    # The same rays on the untransformed model find the same triangles.
    plain = native.Scene(mesh.vertices, mesh.faces)
    base = plain.intersect((origins - offset) / scale, directions / scale)
    moved = scene.intersect(origins, directions)
    same = (base["prim"] == moved["prim"]).mean()
    print(f"{transform}: {same:.6f} of the rays hit the same triangle as untransformed")
    assert same >= 0.999


# ---------------------------------------------------------------------------------------
# Degenerate triangles


def degenerate_scene() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A floor (2 triangles) under zero-area triangles: a point, a triangle with two
    equal corners, three collinear corners in several directions. All coordinates are
    small dyadic numbers and so is the bounding-box centre, so they stay exactly
    degenerate after the scene subtracts the centre and rounds to float."""
    v = [
        (-1, -1, 0),
        (1, -1, 0),
        (1, 1, 0),
        (-1, 1, 0),  # floor
        (0.25, 0.25, 0.5),  # point
        (-0.5, 0.5, 0.25),
        (0.5, -0.5, 0.25),  # two equal corners
        (-0.75, -0.75, 0.75),
        (0.0, 0.0, 0.75),
        (0.75, 0.75, 0.75),  # collinear, diagonal
        (0.5, -0.75, 1.0),
        (0.5, 0.0, 1.0),
        (0.5, 0.75, 1.0),  # collinear, along y
        (-0.5, 0.5, 0.125),
        (-0.25, 0.25, 0.375),
        (0.25, -0.25, 0.875),  # collinear, 3D slope
    ]
    f = [
        (0, 1, 2),
        (0, 2, 3),
        (4, 4, 4),
        (5, 5, 6),
        (5, 6, 6),
        (6, 5, 5),
        (7, 8, 9),
        (8, 7, 9),
        (9, 7, 8),
        (10, 11, 12),
        (12, 10, 11),
        (13, 14, 15),
        (15, 14, 13),
    ]
    vertices = np.array(v, dtype=np.float64)
    faces = np.array(f, dtype=np.uint32)
    degenerate = np.arange(2, len(f))
    return vertices, faces, degenerate


def rays_at_points(targets: np.ndarray, rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Rays from random directions through random points of the given segments/points,
    a fifth of them axis-parallel (exact zeros) and a fifth along the segment itself."""
    pick = rng.integers(0, len(targets), n)
    s = rng.random(n)
    s[: n // 10] = 0.5
    p = targets[pick, 0] + s[:, None] * (targets[pick, 1] - targets[pick, 0])
    d = rng.normal(size=(n, 3))
    axis_rows = np.arange(n // 5)
    d[axis_rows] = 0.0
    d[axis_rows, rng.integers(0, 3, n // 5)] = np.where(rng.random(n // 5) < 0.5, -1.0, 1.0)
    along = np.arange(n // 5, 2 * (n // 5))
    seg = targets[pick[along], 1] - targets[pick[along], 0]
    seg[np.all(seg == 0, axis=1)] = (0.0, 1.0, 0.0)  # a point: any axis will do
    d[along] = seg
    return p - 2.0 * d, d


def test_degenerate_triangles_are_never_hit() -> None:
    vertices, faces, degenerate = degenerate_scene()
    scene = native.Scene(vertices, faces)
    assert scene.triangle_count == len(faces)
    segments = np.stack([vertices[faces[degenerate, 0]], vertices[faces[degenerate, 2]]], axis=1)
    segments = np.concatenate(
        [segments, np.stack([vertices[faces[degenerate, 0]], vertices[faces[degenerate, 1]]], axis=1)]
    )
    origins, directions = rays_at_points(segments, np.random.default_rng(2), 50_000)
    hits = scene.intersect(origins, directions)
    assert not np.isin(hits["prim"], degenerate).any(), "a zero-area triangle was reported hit"
    assert not np.isnan(hits["t"]).any()
    # Everything else is exactly what the floor alone gives.
    floor = native.reference_intersect(vertices, faces[:2], origins, directions)
    np.testing.assert_array_equal(hits["prim"] >= 0, floor["prim"] >= 0)
    found = hits["prim"] >= 0
    # The plain tolerance of compare_with_reference: 1e-5 of max(distance, model size).
    dlen = np.linalg.norm(directions[found], axis=1)
    size = float(np.linalg.norm(vertices.max(axis=0) - vertices.min(axis=0)))
    err = np.abs(hits["t"][found] - floor["t"][found]) * dlen
    assert (err <= 1e-5 * np.maximum(floor["t"][found] * dlen, size)).all()
    np.testing.assert_array_equal(scene.occluded(origins, directions), found)


def test_scene_of_only_degenerate_triangles() -> None:
    vertices, faces, degenerate = degenerate_scene()
    scene = native.Scene(vertices, faces[degenerate])
    segments = np.stack([vertices[faces[degenerate, 0]], vertices[faces[degenerate, 2]]], axis=1)
    origins, directions = rays_at_points(segments, np.random.default_rng(3), 20_000)
    hits = scene.intersect(origins, directions)
    assert (hits["prim"] == -1).all() and np.isinf(hits["t"]).all()
    assert not scene.occluded(origins, directions).any()
    frame = render_view(scene, [2.0, 1.5, 3.0], [0.0, 0.0, 0.5], [0.0, 0.0, 1.0], 60.0, 64, 48)
    assert (frame.prim == -1).all() and np.isinf(frame.depth).all()


# ---------------------------------------------------------------------------------------
# Camera inside a closed model


def view_directions() -> list[tuple[list[float], list[float]]]:
    """(forward, up) for six views covering every direction with fov 100."""
    return [
        ([1, 0, 0], [0, 0, 1]),
        ([-1, 0, 0], [0, 0, 1]),
        ([0, 1, 0], [0, 0, 1]),
        ([0, -1, 0], [0, 0, 1]),
        ([0, 0, 1], [0, 1, 0]),
        ([0, 0, -1], [0, 1, 0]),
    ]


def test_camera_inside_closed_models(
    closed_model_path: Path,
    load_model: Callable[[Path], ModelMesh],
    winding_numbers: Callable[..., np.ndarray],
    reference_check: Callable[..., Agreement],
    camera_directions: Callable[..., np.ndarray],
) -> None:
    """From a point inside (winding number 1: the volume centroid, or the first random
    point near it that is inside), six 100° views cover every direction: every pixel
    hits at a finite positive depth, and what it hits is what the reference hits."""
    mesh = load_model(closed_model_path)
    centroid = trimesh.Trimesh(mesh.vertices, mesh.faces, process=False).center_mass
    jitter = (np.random.default_rng(0).random((200, 3)) - 0.5) * (mesh.hi - mesh.lo) * 0.5
    candidates = np.vstack([centroid, centroid + jitter])
    w = winding_numbers(mesh.vertices, mesh.faces, candidates)
    inside = candidates[np.abs(w - 1) < 1e-3]
    assert len(inside), f"no interior point found in {mesh.name}"
    eye = inside[0]
    scene = native.Scene(mesh.vertices, mesh.faces)
    width, height = 32, 24
    for forward, up in view_directions():
        target = eye + np.array(forward, dtype=np.float64)
        frame = render_view(scene, eye.tolist(), target.tolist(), up, 100.0, width, height)
        prim, depth = frame.prim, frame.depth
        assert (prim >= 0).all(), f"{mesh.name}: {(prim < 0).sum()} pixels see out of a closed mesh"
        assert np.isfinite(depth).all() and (depth > 0).all()
        rays = camera_directions(eye, target, up, 100.0, width, height).reshape(-1, 3)
        origins = np.tile(eye, (len(rays), 1))
        a = reference_check(scene, mesh.vertices, mesh.faces, origins, rays, length=mesh.diagonal)
        assert_agrees(a, f"{mesh.name} inside, looking {forward}")
        assert a.hits == len(rays)
        ours = scene.intersect(origins, rays)
        assert (ours["prim"] == prim.ravel()).mean() >= 0.999


def test_camera_inside_sphere() -> None:
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=2.0)
    scene = native.Scene(
        np.asarray(sphere.vertices, dtype=np.float64), np.asarray(sphere.faces, dtype=np.uint32)
    )
    for forward, up in view_directions():
        frame = render_view(scene, [0.0, 0.0, 0.0], forward, up, 100.0, 40, 40)
        assert (frame.prim >= 0).all()
        # Inscribed radius of the icosphere <= depth <= 2.
        assert (frame.depth > 1.9).all() and (frame.depth <= 2.0 * (1 + 1e-6)).all()


# ---------------------------------------------------------------------------------------
# Shadow rays on a convex, finely tessellated sphere


@pytest.mark.parametrize(
    ("radius", "centre"), [(1.0, (0.0, 0.0, 0.0)), (40.0, (1e6, -2e6, 5e5))], ids=["unit", "far"]
)
def test_sphere_does_not_shadow_itself(
    radius: float, centre: tuple[float, float, float], camera_directions: Callable[..., np.ndarray]
) -> None:
    sphere = trimesh.creation.icosphere(subdivisions=6, radius=radius)
    vertices = np.asarray(sphere.vertices, dtype=np.float64) + np.array(centre)
    faces = np.asarray(sphere.faces, dtype=np.uint32)
    assert len(faces) >= 80_000
    scene = native.Scene(vertices, faces)
    sun = np.array([0.35, 0.8, 0.5])
    sun_unit = sun / np.linalg.norm(sun)
    eye = np.array(centre) + radius * 3.0 * np.array([0.9, -0.5, 0.2])  # sees the terminator
    target = np.array(centre)
    size = 160
    frame = render_view(
        scene, eye.tolist(), target.tolist(), [0, 0, 1], 45.0, size, size, shading="sun", sun=sun.tolist()
    )
    prim = frame.prim
    hit = prim >= 0
    assert hit.mean() > 0.3

    tri = vertices[faces.astype(np.int64)]
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    n = normal[prim[hit]]
    view = camera_directions(eye, target, [0, 0, 1], 45.0, size, size)[hit]
    n = np.where((np.einsum("ij,ij->i", n, view) > 0)[:, None], -n, n)  # facing the viewer
    lam = n @ sun_unit
    grey = frame.image[hit].astype(np.float64).mean(axis=1)
    lit, unlit = lam > 0, lam <= 0
    assert lit.sum() > 1000 and unlit.sum() > 1000
    # One shadow ray per lit pixel (up to pixels whose cosine is zero within rounding).
    borderline = int((np.abs(lam) < 1e-6).sum())
    assert abs(frame.stats.secondary_rays - int(lit.sum())) <= borderline

    # Unlit pixels all sit at one ambient floor; lit ones rise linearly with the cosine.
    floor = float(np.median(grey[unlit]))
    assert np.abs(grey[unlit] - floor).max() <= 1.0
    slope = float(np.linalg.lstsq(lam[lit][:, None], grey[lit] - floor, rcond=None)[0][0])
    assert slope > floor, "lit pixels are not much brighter than the ambient floor"
    residual = np.abs(grey[lit] - (floor + slope * lam[lit]))
    shadowed = lit & (np.abs(grey - floor) <= 1.0) & (lam * slope > 3.0)
    print(
        f"floor {floor:.1f}, slope {slope:.1f}, max residual {residual.max():.2f}, "
        f"{int(shadowed.sum())} shadowed lit pixels of {int(lit.sum())}"
    )
    assert not shadowed.any(), f"{int(shadowed.sum())} lit pixels are in shadow (self-intersection)"
    assert residual.max() <= 2.0

    # occluded() towards the sun from just above every lit hit point finds nothing.
    t = frame.depth[hit][lit].astype(np.float64)
    points = eye + view[lit] * t[:, None] + n[lit] * (1e-5 * radius)
    blocked = scene.occluded(points, np.tile(sun_unit, (len(points), 1)))
    assert not blocked.any(), f"{int(blocked.sum())} shadow rays blocked on a convex sphere"


# ---------------------------------------------------------------------------------------
# Ray batches: empty, invalid, tmin/tmax


def stacked_quads() -> native.Scene:
    """Four 2x2 squares at z = 0, 1, 2, 3 (triangles 2k, 2k+1 at z = k)."""
    vertices, faces = [], []
    for k in range(4):
        base = len(vertices)
        vertices += [(-1, -1, k), (1, -1, k), (1, 1, k), (-1, 1, k)]
        faces += [(base, base + 1, base + 2), (base, base + 2, base + 3)]
    return native.Scene(np.array(vertices, dtype=np.float64), np.array(faces, dtype=np.uint32))


def test_empty_batches() -> None:
    scene = stacked_quads()
    empty = np.zeros((0, 3))
    hits = scene.intersect(empty, empty)
    for key in ("t", "prim", "u", "v"):
        assert hits[key].shape == (0,)
    assert hits["node_visits"] == 0 and hits["triangle_tests"] == 0
    assert scene.occluded(empty, empty).shape == (0,)
    ref = native.reference_intersect(np.eye(3), np.array([[0, 1, 2]], dtype=np.uint32), empty, empty)
    assert ref["t"].shape == (0,)


def test_invalid_rays_miss() -> None:
    scene = stacked_quads()
    nan, inf = math.nan, math.inf
    good_o, good_d = (0.1, 0.2, -1.0), (0.0, 0.0, 1.0)
    cases = [
        ((nan, 0.2, -1.0), good_d, 0.0, inf),
        (good_o, (0.0, nan, 1.0), 0.0, inf),
        (good_o, (0.0, 0.0, 0.0), 0.0, inf),
        (good_o, (0.0, -0.0, -0.0), 0.0, inf),
        (good_o, (0.0, 0.0, inf), 0.0, inf),
        ((0.1, inf, -1.0), good_d, 0.0, inf),
        (good_o, good_d, nan, inf),
        (good_o, good_d, 0.0, nan),
        (good_o, good_d, 2.0, 1.0),  # empty interval
    ]
    o = np.array([c[0] for c in cases] + [good_o])
    d = np.array([c[1] for c in cases] + [good_d])
    tmin = np.array([c[2] for c in cases] + [0.0])
    tmax = np.array([c[3] for c in cases] + [inf])
    hits = scene.intersect(o, d, tmin, tmax)
    assert (hits["prim"][:-1] == -1).all(), hits["prim"]
    assert np.isinf(hits["t"][:-1]).all()
    assert not np.isnan(hits["u"]).any() and not np.isnan(hits["v"]).any()
    assert hits["prim"][-1] in (0, 1) and hits["t"][-1] == pytest.approx(1.0)  # valid ray still hits
    occluded = scene.occluded(o, d, tmin, tmax)
    assert not occluded[:-1].any() and occluded[-1]


def test_tmin_and_tmax_are_respected() -> None:
    scene = stacked_quads()
    o = np.tile([0.1, 0.2, -1.0], (9, 1))
    d = np.tile([0.0, 0.0, 2.0], (9, 1))  # planes at t = 0.5, 1, 1.5, 2
    tmin = np.array([0.0, 0.6, 0.6, 1.2, 1.2, 1.6, 2.1, 0.0, 0.0])
    tmax = np.array([np.inf, np.inf, 1.4, 1.4, 1.6, 1.9, np.inf, 0.4, 0.75])
    expected = np.array([0.5, 1.0, 1.0, np.inf, 1.5, np.inf, np.inf, np.inf, 0.5])
    hits = scene.intersect(o, d, tmin, tmax)
    np.testing.assert_allclose(hits["t"], expected, rtol=1e-6)
    plane = np.where(np.isfinite(expected), np.rint(expected * 2 - 1), -1)
    np.testing.assert_array_equal(np.where(hits["prim"] >= 0, hits["prim"] // 2, -1), plane)
    np.testing.assert_array_equal(scene.occluded(o, d, tmin, tmax), np.isfinite(expected))
    # Scalars broadcast.
    assert scene.intersect(o, d, 0.6, 1.4)["t"] == pytest.approx(np.ones(9))


def test_random_tmin_tmax_against_reference(
    small_closed_model: ModelMesh, reference_check: Callable[..., Agreement]
) -> None:
    mesh = small_closed_model
    rng = np.random.default_rng(9)
    n = 30_000
    sphere = rng.normal(size=(n, 3))
    sphere /= np.linalg.norm(sphere, axis=1, keepdims=True)
    centre = (mesh.lo + mesh.hi) / 2
    origins = centre + sphere * mesh.diagonal
    directions = mesh.lo + rng.random((n, 3)) * (mesh.hi - mesh.lo) - origins
    tmin = rng.uniform(0.0, 1.2, n)
    tmax = tmin + rng.uniform(0.0, 1.0, n)
    scene = native.Scene(mesh.vertices, mesh.faces)
    a = reference_check(
        scene, mesh.vertices, mesh.faces, origins, directions, length=mesh.diagonal, tmin=tmin, tmax=tmax
    )
    assert_agrees(a, f"{mesh.name} with tmin/tmax")
    hits = scene.intersect(origins, directions, tmin, tmax)
    found = hits["prim"] >= 0
    assert found.mean() > 0.1
    assert (hits["t"][found] >= tmin[found] * (1 - 1e-6)).all()
    assert (hits["t"][found] <= tmax[found] * (1 + 1e-6)).all()


# ---------------------------------------------------------------------------------------
# Bad input: clear errors


def quad() -> tuple[np.ndarray, np.ndarray]:
    return (
        np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], dtype=np.float64),
        np.array([[0, 1, 2], [0, 2, 3]], dtype=np.uint32),
    )


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"faces": np.zeros((0, 3), dtype=np.uint32)}, "no triangles"),
        ({"vertex": (2, math.nan)}, "not finite"),
        ({"vertex": (1, math.inf)}, "not finite"),
        ({"vertex": (3, -math.inf)}, "not finite"),
        ({"vertex": (2, 1e39)}, "float range"),
        ({"faces": np.array([[0, 1, 4]], dtype=np.uint32)}, "vertex 4"),
        ({"faces": np.array([[0, 1, 2], [0, 2, 2**31]], dtype=np.uint32)}, "vertex"),
        ({"vertices": np.zeros((4, 2))}, "shape"),
        ({"faces": np.array([[0, 1, 2, 3]], dtype=np.uint32)}, "shape"),
        ({"colours": np.zeros((3, 3), dtype=np.uint8)}, "one row per face"),
        ({"colours": np.zeros((2, 4), dtype=np.uint8)}, "shape"),
        ({"leaf_size": 0}, "parameters"),
        ({"bins": 1}, "parameters"),
        ({"traversal_cost": -1.0}, "parameters"),
    ],
)
def test_bad_scene_input_raises(change: dict[str, object], message: str) -> None:
    vertices, faces = quad()
    kwargs: dict[str, object] = {}
    for key, value in change.items():
        if key == "vertex":
            row, x = value  # type: ignore[misc]
            vertices[row, 1] = x
        elif key == "vertices":
            vertices = value  # type: ignore[assignment]
        elif key == "faces":
            faces = value  # type: ignore[assignment]
        else:
            kwargs[key] = value
    with pytest.raises(ValueError, match=message):
        native.Scene(vertices, faces, **kwargs)


def test_bad_ray_arrays_raise() -> None:
    scene = stacked_quads()
    o = np.zeros((4, 3))
    with pytest.raises(ValueError, match="differ in length"):
        scene.intersect(o, np.ones((3, 3)))
    with pytest.raises(ValueError, match="shape"):
        scene.intersect(np.zeros((4, 2)), np.ones((4, 2)))
    with pytest.raises(ValueError, match="one value per ray"):
        scene.occluded(o, np.ones((4, 3)), np.zeros(3))


CAMERA = {
    "eye": [3.0, -4.0, 2.0],
    "target": [0.0, 0.0, 1.5],
    "up": [0.0, 0.0, 1.0],
    "fov": 50.0,
    "width": 32,
    "height": 24,
}


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"eye": [math.nan, 0.0, 0.0]}, "finite"),
        ({"target": [0.0, math.inf, 0.0]}, "finite"),
        ({"up": [0.0, 0.0, math.nan]}, "finite"),
        ({"fov": math.nan}, "finite"),
        ({"target": [3.0, -4.0, 2.0]}, "eye and target"),
        ({"up": [0.0, 0.0, 0.0]}, "up"),
        ({"up": [-3.0, 4.0, -0.5]}, "parallel"),
        ({"fov": 0.0}, "fov"),
        ({"fov": 180.0}, "fov"),
        ({"fov": -30.0}, "fov"),
        ({"width": 0}, "size"),
        ({"height": -2}, "size"),
        ({"width": 100_000}, "size"),
        ({"sun": [0.0, 0.0, 0.0]}, "sun"),
        ({"sun": [math.nan, 1.0, 0.0]}, "sun"),
        ({"ao_samples": 0}, "ao_samples"),
        ({"shading": "phong"}, "phong"),
        ({"shading": ""}, "shading"),
    ],
)
def test_bad_camera_raises_with_clear_message(change: dict[str, object], message: str) -> None:
    scene = stacked_quads()
    kwargs = {**CAMERA, **change}
    with pytest.raises(ValueError, match=message):
        render_view(scene, **kwargs)
    # Nothing changed: the same scene still renders.
    frame = render_view(scene, **CAMERA)
    assert (frame.prim >= 0).any()


def test_axis_parallel_rays_do_not_degrade_to_brute_force(small_closed_model: ModelMesh) -> None:
    """Rays with zero direction components give infinite split distances; the traversal
    must still visit only the cells along the ray. Work counters, not timings: an axis ray
    tests a small fraction of the model's triangles, as an oblique ray does."""
    mesh = small_closed_model
    scene = native.Scene(mesh.vertices, mesh.faces)
    rng = np.random.default_rng(11)
    lo, hi = mesh.vertices.min(axis=0), mesh.vertices.max(axis=0)
    n = 4000
    origins = lo + rng.random((n, 3)) * (hi - lo)
    axis = rng.integers(0, 3, n)
    directions = np.zeros((n, 3))
    directions[np.arange(n), axis] = np.where(rng.random(n) < 0.5, -1.0, 1.0)
    directions[directions == 0] = np.where(rng.random((directions == 0).sum()) < 0.5, -0.0, 0.0)
    axis_hits = scene.intersect(origins, directions)
    oblique = scene.intersect(origins, rng.normal(size=(n, 3)))
    per_ray_axis = axis_hits["triangle_tests"] / n
    per_ray_oblique = oblique["triangle_tests"] / n
    assert per_ray_axis < 0.02 * len(mesh.faces)
    assert per_ray_axis < 10 * per_ray_oblique + 10
