"""scene.intersect / scene.occluded against an independent float64 brute-force reference.

Acceptance bar: on >= 10^5 random rays per real mesh, the kd-tree + watertight float32
intersector and `native.reference_intersect` (double Möller–Trumbore over every
triangle) give the same hit/miss, t within 1e-5 relative, and the same triangle unless
two are tied. `compare_with_reference` in conftest.py does the classification:

* t tolerance: ``|t - t_ref| * |d| <= 1e-5 * max(t_ref * |d|, L) + 8 eps32 L / |cos θ|``
  with L the model's bounding-box diagonal and θ the angle between the ray and the
  reference triangle's normal. The first term is relative to the hit distance but never
  tighter than 1e-5 of the model size, since float32 geometry carries an absolute error
  proportional to the model size (a ray starting inside the model can hit at t -> 0);
  for the rays from outside, t_ref * |d| is of the order of L, so this is the plain
  relative bound. The second term only matters at grazing incidence: rounding moves the
  surface by a few eps32 L perpendicular to itself, which a ray at angle θ sees 1/|cos θ|
  times as far along it (a fandisk ray at cos θ = 4e-4 is off by 1.7e-5 L). The rays that
  need it are counted (0 or 1 per mesh).
* tied: either the reference's second-closest distinct hit is within that tolerance of
  its closest hit (two surfaces at the same distance), or our triangle and the
  reference's share a corner position and the reference hit's smallest barycentric
  coordinate (1-u-v, u, v) is below 1e-4: a float32 ray through a shared edge or vertex
  may fairly pick either side. In both cases our triangle, intersected in double, must
  be hit within the t tolerance and at most 1e-4 (barycentric) outside its edges.
* hit/miss must agree, except at a silhouette: a ray whose hit (the reference's, or
  ours measured in double) is within 1e-5 (barycentric) of the triangle's edge and the
  other side does not see it (also when both hit, but the nearer hit is such an edge
  contact). Those are counted and must be at most 1e-5 of the rays, i.e. one ray per
  mesh (measured: zero on every mesh).
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from vastray import native

if TYPE_CHECKING:
    from conftest import Agreement, ModelMesh

OUTSIDE_RAYS = 100_000
INSIDE_RAYS = 20_000


def random_rays(mesh: ModelMesh, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Rays from a sphere of radius ~ the diagonal aimed at random points of the box, then
    rays from random points inside the box in random directions of random length (t is
    in units of the given direction, so the length must not matter)."""
    lo, hi = mesh.lo, mesh.hi
    centre, diag = (lo + hi) / 2, mesh.diagonal
    sphere = rng.normal(size=(OUTSIDE_RAYS, 3))
    sphere /= np.linalg.norm(sphere, axis=1, keepdims=True)
    o1 = centre + sphere * diag * rng.uniform(0.8, 1.2, size=(OUTSIDE_RAYS, 1))
    d1 = lo + rng.random((OUTSIDE_RAYS, 3)) * (hi - lo) - o1
    o2 = lo + rng.random((INSIDE_RAYS, 3)) * (hi - lo)
    d2 = rng.normal(size=(INSIDE_RAYS, 3))
    d2 *= diag * rng.uniform(0.01, 10.0, size=(INSIDE_RAYS, 1)) / np.linalg.norm(d2, axis=1, keepdims=True)
    return np.vstack([o1, o2]), np.vstack([d1, d2])


def test_matches_reference(
    model_path: Path,
    load_model: Callable[[Path], ModelMesh],
    reference_check: Callable[..., Agreement],
) -> None:
    mesh = load_model(model_path)
    scene = native.Scene(mesh.vertices, mesh.faces)
    origins, directions = random_rays(mesh, np.random.default_rng(20240601))
    a = reference_check(scene, mesh.vertices, mesh.faces, origins, directions, length=mesh.diagonal)
    print(f"{mesh.name}: {a.summary()}")

    assert a.rays >= 100_000
    assert a.hits > 0.3 * a.rays  # the rays really meet the model
    assert a.nonfinite == 0
    assert len(a.bad_mismatches) == 0, f"hit/miss disagrees away from edges: rays {a.bad_mismatches[:10]}"
    assert a.graze_mismatches <= 1e-5 * a.rays
    assert len(a.bad_t) == 0, f"t off by more than the tolerance: rays {a.bad_t[:10]}"
    assert len(a.bad_prims) == 0, f"different triangle without a tie: rays {a.bad_prims[:10]}"
    # The reported barycentrics locate the same point as the reference's t.
    assert a.max_point_error <= 1.0


def test_occluded_agrees_with_closest_hit(model_path: Path, load_model: Callable[[Path], ModelMesh]) -> None:
    """Any-hit queries see the same surfaces, and respect tmax on both sides of the hit."""
    mesh = load_model(model_path)
    scene = native.Scene(mesh.vertices, mesh.faces)
    origins, directions = random_rays(mesh, np.random.default_rng(7))
    origins, directions = origins[::4], directions[::4]
    hits = scene.intersect(origins, directions)
    t, hit = hits["t"], hits["prim"] >= 0
    np.testing.assert_array_equal(scene.occluded(origins, directions), hit)
    # Nothing is closer than the closest hit, and the closest hit is inside [0, 1.001 t].
    assert not scene.occluded(origins[hit], directions[hit], 0.0, t[hit] * (1 - 1e-3)).any()
    assert scene.occluded(origins[hit], directions[hit], 0.0, t[hit] * (1 + 1e-3)).all()
    # With tmin past the closest hit, closest-hit queries report something further on.
    later = scene.intersect(origins[hit], directions[hit], t[hit] * (1 + 1e-3))
    found = later["prim"] >= 0
    assert (later["t"][found] >= t[hit][found] * (1 + 1e-3)).all()


def test_reference_culling_changes_nothing(small_closed_model: ModelMesh) -> None:
    """The reference's bounding-box culling against pure brute force, and our intersector
    against both, on 2000 rays on the smallest closed real mesh."""
    mesh = small_closed_model
    origins, directions = random_rays(mesh, np.random.default_rng(3))
    pick = np.r_[0:1500, OUTSIDE_RAYS : OUTSIDE_RAYS + 500]
    origins, directions = origins[pick], directions[pick]
    culled = native.reference_intersect(mesh.vertices, mesh.faces, origins, directions, cull=True)
    brute = native.reference_intersect(mesh.vertices, mesh.faces, origins, directions, cull=False)
    for key in ("t", "t_second", "prim", "u", "v"):
        np.testing.assert_array_equal(culled[key], brute[key], err_msg=key)
    assert (brute["prim"] >= 0).sum() > 500

    ours = native.Scene(mesh.vertices, mesh.faces).intersect(origins, directions)
    np.testing.assert_array_equal(ours["prim"] >= 0, brute["prim"] >= 0)
    hit = brute["prim"] >= 0
    # The same plain tolerance as compare_with_reference: relative, floored at the model size.
    scale = np.maximum(brute["t"][hit], mesh.diagonal / np.linalg.norm(directions[hit], axis=1))
    assert (np.abs(ours["t"][hit] - brute["t"][hit]) <= 1e-5 * scale).all()
