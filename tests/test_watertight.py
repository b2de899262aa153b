"""Watertightness: rays aimed exactly at vertices and edge points of closed meshes never leak.

Acceptance bar: ">= 10^6 rays aimed exactly at vertices and at edge points of the closed
meshes, from inside and outside: zero leaks". Each of the five closed models gets at
least 2*10^5 kept rays (so >= 10^6 in all), in three kinds:

* from outside, origins on a sphere of radius 2x the bounding-box diagonal around the
  centre, direction = target - origin (so the target lies at t = 1);
* from outside, axis-parallel: the origin is the target with one coordinate moved out
  of the box, the other two direction components are +0 or -0. The scene converts
  ``origin - centre`` to float exactly as it converts the vertex, so these float32 rays
  pass *exactly* through the stored vertex (edge functions exactly zero), the case the
  watertight test's double-precision fallback exists for;
* from inside: origins whose generalised winding number (sum of solid angles / 4π,
  computed in numpy, independent of the ray tracer) is ±1.

Targets are every vertex, every edge midpoint (s = 0.5 exactly) and points
p0 + s (p1 - p0) with random s, computed in double.

A ray that crosses the surface at its target must hit at t <= 1 (+ rounding). That is
only certain where the surface really is crossed there, so targets are kept only when
every triangle around them (the vertex's star; for an edge point the stars of both
endpoints) faces the ray on the same side with |cos| >= 0.05; the mesh is checked to be
closed and consistently oriented, so the ray then passes through that patch however
float rounding (about 1e-6 of the model size) nudges it. Grazing/silhouette targets
are dropped and their count reported.

A leak is any kept ray that misses, or hits beyond t = 1 + 1e-4 * L / |d| (L: the
diagonal; the patch can lie at most ~2e-5 L behind the target along a ray at
|cos| >= 0.05), or hits beyond t = 1 on a triangle that does not touch the target's
patch (it went through and found another surface just behind). Hits before t = 1 on
any triangle are fine: something in front occludes the target.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from vastray import native

if TYPE_CHECKING:
    from conftest import ModelMesh

MIN_RAYS_PER_MESH = 200_000
COS_MARGIN = 0.05
T_SLACK = 1e-4  # of the model diagonal, along the ray
INTERIOR_POINTS = 64
CHUNK = 50_000


def merged(mesh: ModelMesh) -> tuple[np.ndarray, np.ndarray]:
    """Vertices with duplicate positions merged (spot is split at texture seams)."""
    vertices, inverse = np.unique(mesh.vertices, axis=0, return_inverse=True)
    return vertices, inverse.reshape(-1)[mesh.faces.astype(np.int64)].astype(np.uint32)


def unique_edges(faces: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(undirected unique edges, how often each occurs, directed edge list)."""
    f = faces.astype(np.int64)
    directed = np.stack([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]], axis=1).reshape(-1, 2)
    edges, counts = np.unique(np.sort(directed, axis=1), axis=0, return_counts=True)
    return edges, counts, directed


def vertex_stars(faces: np.ndarray, vertex_count: int) -> np.ndarray:
    """(V, K) faces around each vertex, padded with -1."""
    corner_vertex = faces.astype(np.int64).reshape(-1)
    corner_face = np.repeat(np.arange(faces.shape[0]), 3)
    order = np.argsort(corner_vertex, kind="stable")
    corner_vertex, corner_face = corner_vertex[order], corner_face[order]
    valence = np.bincount(corner_vertex, minlength=vertex_count)
    start = np.concatenate([[0], np.cumsum(valence)[:-1]])
    slot = np.arange(corner_vertex.size) - start[corner_vertex]
    stars = np.full((vertex_count, int(valence.max())), -1, dtype=np.int64)
    stars[corner_vertex, slot] = corner_face
    return stars


def interior_points(
    vertices: np.ndarray,
    faces: np.ndarray,
    rng: np.random.Generator,
    winding_numbers: Callable[..., np.ndarray],
) -> np.ndarray:
    """Points with winding number ±1 (inside, whichever way the mesh is oriented): random
    box points and points just behind faces."""
    lo, hi = vertices.min(axis=0), vertices.max(axis=0)
    diag = float(np.linalg.norm(hi - lo))
    tri = vertices[faces.astype(np.int64)]
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    pick = rng.choice(len(faces), INTERIOR_POINTS, replace=False)
    behind = tri[pick].mean(axis=1) - normal[pick] * 2e-3 * diag
    box = lo + rng.random((2 * INTERIOR_POINTS, 3)) * (hi - lo)
    candidates = np.vstack([box, behind])
    w = winding_numbers(vertices, faces, candidates)
    inside = candidates[np.abs(np.abs(w) - 1.0) < 1e-3]
    assert len(inside) >= 16, f"found only {len(inside)} interior points"
    return inside[:INTERIOR_POINTS]


def shoot(
    scene: native.Scene,
    faces: np.ndarray,
    normal: np.ndarray,
    stars: np.ndarray,
    diag: float,
    origins: np.ndarray,
    directions: np.ndarray,
    ends_a: np.ndarray,
    ends_b: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, float]:
    """Filters out grazing targets, traces the rest; returns (kept mask, indices of the
    leaks among the input rays, max (t - 1) |d| / L over the kept hits)."""
    # Keep targets whose whole patch faces the ray on one side, away from grazing.
    dunit = directions / np.linalg.norm(directions, axis=1, keepdims=True)
    patch = np.hstack([stars[ends_a], stars[ends_b]])
    cos = np.einsum("nkj,nj->nk", normal[np.maximum(patch, 0)], dunit)
    cos = np.where(patch >= 0, cos, np.nan)
    ok = (np.nanmin(cos, axis=1) >= COS_MARGIN) | (np.nanmax(cos, axis=1) <= -COS_MARGIN)
    idx = np.flatnonzero(ok)
    hit = scene.intersect(origins[idx], directions[idx])
    t, prim = hit["t"], hit["prim"]
    assert not np.isnan(t).any()
    dlen = np.linalg.norm(directions[idx], axis=1)
    slack = T_SLACK * diag / dlen
    corners = faces[np.maximum(prim, 0)].astype(np.int64)
    a, b = ends_a[idx], ends_b[idx]
    touches = (corners == a[:, None]).any(axis=1) | (corners == b[:, None]).any(axis=1)
    leak = (prim < 0) | (t > 1 + slack) | ((t > 1) & ~touches)
    found = prim >= 0
    # Any-hit rays (the wide BVH's quads, whose lanes hand exact edge hits to the scalar
    # test) close the same surface: a ray to a target sees it, or something before it.
    tmax = 1 + slack
    blocked = scene.occluded(origins[idx], directions[idx], 0.0, tmax)
    np.testing.assert_array_equal(blocked, found & (t < tmax))
    excess = float(((t[found] - 1) * dlen[found] / diag).max(initial=0.0))
    return ok, idx[leak], excess


def test_closed_meshes_do_not_leak(
    closed_model_path: Path,
    load_model: Callable[[Path], ModelMesh],
    winding_numbers: Callable[..., np.ndarray],
) -> None:
    mesh = load_model(closed_model_path)
    vertices, faces = merged(mesh)
    edges, counts, directed = unique_edges(faces)
    # Preconditions that make "must hit" true: closed, consistently oriented.
    assert (counts == 2).all(), f"{mesh.name} is not closed"
    assert len(np.unique(directed, axis=0)) == len(directed), f"{mesh.name} is not oriented"

    rng = np.random.default_rng(12345)
    scene = native.Scene(vertices, faces)
    lo, hi = vertices.min(axis=0), vertices.max(axis=0)
    centre, diag = (lo + hi) / 2, float(np.linalg.norm(hi - lo))
    tri = vertices[faces.astype(np.int64)]
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    stars = vertex_stars(faces, len(vertices))
    inside = interior_points(vertices, faces, rng, winding_numbers)

    kept = {"outside": 0, "axis": 0, "inside": 0}
    dropped = 0
    exact_vertex_rays = 0
    leaks = 0
    examples: list[str] = []
    max_excess = 0.0
    rounds = 0
    while sum(kept.values()) < MIN_RAYS_PER_MESH:
        rounds += 1
        # Targets: (point, endpoint a, endpoint b); a == b for a vertex.
        s = np.concatenate([np.full(len(edges), 0.5), rng.random(len(edges))])
        e = np.vstack([edges, edges])
        p0, p1 = vertices[e[:, 0]], vertices[e[:, 1]]
        targets = np.vstack([vertices, p0 + s[:, None] * (p1 - p0)])
        ends_a = np.concatenate([np.arange(len(vertices)), e[:, 0]])
        ends_b = np.concatenate([np.arange(len(vertices)), e[:, 1]])
        is_vertex = np.arange(len(targets)) < len(vertices)

        for kind in kept:
            n = len(targets)
            if kind == "outside":
                sphere = rng.normal(size=(n, 3))
                sphere /= np.linalg.norm(sphere, axis=1, keepdims=True)
                origins = centre + 2.0 * diag * sphere
            elif kind == "axis":
                axis = rng.integers(0, 3, n)
                side = rng.integers(0, 2, n)
                origins = targets.copy()
                rows = np.arange(n)
                origins[rows, axis] = np.where(side == 0, lo[axis] - 0.5 * diag, hi[axis] + 0.5 * diag)
            else:
                origins = inside[rng.integers(0, len(inside), n)]
            directions = targets - origins
            if kind == "axis":
                # The two zero components get random signs: +0 and -0 must behave alike.
                zero = directions == 0
                directions[zero] = np.where(rng.random(int(zero.sum())) < 0.5, 0.0, -0.0)
            for chunk in np.array_split(np.arange(n), -(-n // CHUNK)):
                ok, leak, excess = shoot(
                    scene,
                    faces,
                    normal,
                    stars,
                    diag,
                    origins[chunk],
                    directions[chunk],
                    ends_a[chunk],
                    ends_b[chunk],
                )
                kept[kind] += int(ok.sum())
                dropped += int((~ok).sum())
                if kind == "axis":
                    exact_vertex_rays += int((ok & is_vertex[chunk]).sum())
                max_excess = max(max_excess, excess)
                leaks += len(leak)
                for j in chunk[leak[: max(0, 5 - len(examples))]]:
                    examples.append(
                        f"{kind}: origin {origins[j].tolist()} direction {directions[j].tolist()}"
                    )

    total = sum(kept.values())
    print(
        f"{mesh.name}: {total} rays in {rounds} rounds ({kept}), {exact_vertex_rays} axis rays "
        f"exactly through vertices, {dropped} grazing targets dropped, "
        f"{leaks} leaks, max (t - 1) |d| / L = {max_excess:.3g}"
    )
    assert total >= MIN_RAYS_PER_MESH
    assert leaks == 0, f"{leaks} leaks, e.g. " + "; ".join(examples)
