"""Shared fixtures for the test suite.

Real meshes: the models folder is ``$VASTRAY_MODELS`` or ``<repo>/../shared/models``.
Tests that take a ``model_path`` argument run once per ``.obj`` there;
``closed_model_path`` runs over the models its README lists as closed (watertight).
``load_model(path)`` loads one (cached), ``small_closed_model`` is the smallest closed one.

Helpers handed out as fixtures (so test modules never import conftest):
``reference_check`` (compare scene.intersect with native.reference_intersect and classify
every disagreement), ``winding_numbers`` (inside/outside without ray tracing) and
``camera_directions`` (the documented camera model in numpy).
"""

from __future__ import annotations

import os
import warnings
from collections.abc import Callable
from dataclasses import dataclass
from functools import cache
from pathlib import Path

import numpy as np
import pytest

from vastray import native

# Child Pythons the tests start run from the repository root, where the source folder
# `vastray/` (without the compiled module) would shadow the installed package: the tests
# exercise the package as installed, so no child puts its working directory first.
os.environ["PYTHONSAFEPATH"] = "1"

FLOAT32_EPS = float(np.finfo(np.float32).eps)

REPO_ROOT = Path(__file__).resolve().parent.parent

# Closed (watertight) once duplicate positions are merged; see the models README.
CLOSED_MODELS = ("nefertiti", "rocker-arm", "fandisk", "cow", "spot")


def models_dir() -> Path:
    return Path(os.environ.get("VASTRAY_MODELS", REPO_ROOT.parent / "shared" / "models"))


def model_paths() -> list[Path]:
    # The real meshes are part of the acceptance bar: a missing folder is an error, not
    # a reason to skip (CI has ../shared beside the clone).
    folder = models_dir()
    if not folder.is_dir():
        raise FileNotFoundError(f"models folder not found at {folder}; set VASTRAY_MODELS")
    return sorted(folder.glob("*.obj"))


@dataclass(frozen=True)
class ModelMesh:
    vertices: np.ndarray  # (V, 3) float64
    faces: np.ndarray  # (F, 3) uint32
    name: str

    @property
    def lo(self) -> np.ndarray:
        return self.vertices[self.faces.ravel()].min(axis=0)

    @property
    def hi(self) -> np.ndarray:
        return self.vertices[self.faces.ravel()].max(axis=0)

    @property
    def diagonal(self) -> float:
        return float(np.linalg.norm(self.hi - self.lo))


@cache
def _load(path: Path) -> ModelMesh:
    try:
        from vastray.ingest import load_mesh
    except ImportError:  # ingest not there yet: read the file the same way it would
        import trimesh

        m = trimesh.load(path, process=False, force="mesh")
        vertices, faces = np.asarray(m.vertices), np.asarray(m.faces)
    else:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            mesh = load_mesh(path)
        vertices, faces = mesh.vertices, mesh.faces
    v = np.ascontiguousarray(vertices, dtype=np.float64)
    f = np.ascontiguousarray(faces, dtype=np.uint32)
    v.setflags(write=False)
    f.setflags(write=False)
    return ModelMesh(v, f, path.stem)


def pytest_generate_tests(metafunc: pytest.Metafunc) -> None:
    # Only tests that take a mesh depend on the models folder being there.
    if "model_path" in metafunc.fixturenames:
        paths = model_paths()
        metafunc.parametrize("model_path", paths, ids=[p.stem for p in paths])
    if "closed_model_path" in metafunc.fixturenames:
        closed = [p for p in model_paths() if p.stem in CLOSED_MODELS]
        metafunc.parametrize("closed_model_path", closed, ids=[p.stem for p in closed])


@pytest.fixture(scope="session")
def models_folder() -> Path:
    return models_dir()


@pytest.fixture(scope="session")
def load_model() -> Callable[[Path], ModelMesh]:
    """Loads a mesh (cached, read-only arrays) through vastray.ingest when available."""
    return _load


def winding_numbers(vertices: np.ndarray, faces: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Generalised winding number of each point: the sum of the solid angles of the
    triangles seen from it over 4π (Van Oosterom–Strackee), ~1 inside an outward-oriented
    closed mesh, ~0 outside. Plain numpy, independent of the ray tracer."""
    tri = vertices[faces.astype(np.int64)]
    out = np.empty(len(points))
    for i, p in enumerate(np.asarray(points, dtype=np.float64)):
        a, b, c = tri[:, 0] - p, tri[:, 1] - p, tri[:, 2] - p
        la, lb, lc = (np.linalg.norm(x, axis=1) for x in (a, b, c))
        det = np.einsum("ij,ij->i", a, np.cross(b, c))
        den = (
            la * lb * lc
            + np.einsum("ij,ij->i", a, b) * lc
            + np.einsum("ij,ij->i", a, c) * lb
            + np.einsum("ij,ij->i", b, c) * la
        )
        out[i] = np.arctan2(det, den).sum() / (2.0 * np.pi)
    return out


@pytest.fixture(scope="session", name="winding_numbers")
def winding_numbers_fixture() -> Callable[..., np.ndarray]:
    """`winding_numbers(vertices, faces, points)`: inside/outside without ray tracing."""
    return winding_numbers


def camera_directions(
    eye: np.ndarray, target: np.ndarray, up: np.ndarray | list[float], fov: float, width: int, height: int
) -> np.ndarray:
    """(H, W, 3) unit view rays of the documented camera model, computed in numpy
    (`vastray.camera.Camera.primary_rays`), to check the native renderer against."""
    from vastray.camera import Camera

    def as_vec(a: np.ndarray | list[float]) -> tuple[float, float, float]:
        return (float(a[0]), float(a[1]), float(a[2]))

    _, dirs = Camera(as_vec(eye), as_vec(target), as_vec(up), fov, width, height).primary_rays()
    return dirs.reshape(height, width, 3)


@pytest.fixture(scope="session", name="camera_directions")
def camera_directions_fixture() -> Callable[..., np.ndarray]:
    return camera_directions


@pytest.fixture(scope="session")
def small_closed_model() -> ModelMesh:
    """The smallest closed real mesh, for tests that need one but not all of them."""
    closed = [p for p in model_paths() if p.stem in CLOSED_MODELS]
    if not closed:
        pytest.skip(f"no closed models in {models_dir()}")
    return min((_load(p) for p in closed), key=lambda m: m.faces.shape[0])


# ----------------------------------------------------------------------------------------
# Agreement with the independent double-precision reference (native.reference_intersect)


def triangle_hits(
    vertices: np.ndarray,
    faces: np.ndarray,
    prim: np.ndarray,
    origins: np.ndarray,
    directions: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Double-precision Möller–Trumbore of ray i against triangle prim[i]: (t, u, v), no
    range checks, so callers can see how far outside the triangle a ray passes."""
    p0, p1, p2 = (vertices[faces[prim, k].astype(np.int64)] for k in range(3))
    e1, e2 = p1 - p0, p2 - p0
    pv = np.cross(directions, e2)
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / np.einsum("ij,ij->i", e1, pv)
        tv = origins - p0
        qv = np.cross(tv, e1)
        u = np.einsum("ij,ij->i", tv, pv) * inv
        v = np.einsum("ij,ij->i", directions, qv) * inv
        t = np.einsum("ij,ij->i", e2, qv) * inv
    return t, u, v


def min_barycentric(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    u = np.asarray(u, dtype=np.float64)
    v = np.asarray(v, dtype=np.float64)
    return np.minimum(np.minimum(1.0 - u - v, u), v)


def share_a_vertex(vertices: np.ndarray, faces: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Triangles a[i] and b[i] have a corner at the same position (by coordinates, so
    triangles across a texture seam with duplicated positions count as neighbours)."""
    pa = vertices[faces[a].astype(np.int64)]  # (n, 3, 3)
    pb = vertices[faces[b].astype(np.int64)]
    same = (pa[:, :, None, :] == pb[:, None, :, :]).all(axis=-1)  # (n, 3, 3)
    return same.any(axis=(1, 2))


@dataclass
class Agreement:
    """How `scene.intersect` compares with the reference on one batch of rays."""

    rays: int
    hits: int
    graze_mismatches: int  # disagreements at an edge (tolerated, reported)
    bad_mismatches: np.ndarray  # ray ids: hit/miss disagreements away from any edge
    ties: int  # a different triangle, explained by a tie
    bad_prims: np.ndarray  # ray ids: a different triangle and no tie
    bad_t: np.ndarray  # ray ids: t outside the tolerance
    grazing_t: int  # t within tolerance only thanks to the grazing-incidence term
    max_t_error: float  # max over common hits of |t - t_ref| / tolerance (<= 1 passes)
    max_rel_t_error: float  # max of |t - t_ref| / t_ref: plain relative error, reported
    max_point_error: float  # max |hit point from our (prim, u, v) - reference point| / tolerance
    nonfinite: int  # NaN anywhere in the outputs, or a finite t with prim -1 and so on

    def summary(self) -> str:
        return (
            f"{self.rays} rays, {self.hits} hits, {self.graze_mismatches} grazing disagreements, "
            f"{len(self.bad_mismatches)} other hit/miss mismatches, {self.ties} ties, "
            f"{len(self.bad_prims)} wrong triangles, {len(self.bad_t)} t errors "
            f"({self.grazing_t} within tolerance only at grazing incidence), "
            f"max t error {self.max_t_error:.3g} of tolerance (relative {self.max_rel_t_error:.3g}), "
            f"max point error {self.max_point_error:.3g} of tolerance, {self.nonfinite} non-finite"
        )


def compare_with_reference(
    scene: object,
    vertices: np.ndarray,
    faces: np.ndarray,
    origins: np.ndarray,
    directions: np.ndarray,
    *,
    length: float,
    tmin: float | np.ndarray = 0.0,
    tmax: float | np.ndarray = np.inf,
    rel: float = 1e-5,
    abs_distance: float = 0.0,
    tie_bary: float = 1e-4,
    graze_bary: float = 1e-5,
    grazing_eps: float = 8 * FLOAT32_EPS,
) -> Agreement:
    """Runs both intersectors and classifies every disagreement.

    Distance tolerance per ray: ``rel * max(t_ref * |d|, length) + abs_distance`` (the
    *plain* tolerance: relative to the hit distance but never below ``rel`` of the model
    size ``length``, since float32 geometry has an absolute error that scales with the
    model, not with t), plus ``grazing_eps * length / |cos θ|`` with θ the angle between
    the ray and the reference triangle's normal: float32 rounding of the origin and the
    vertices (at most eps32 * length / 2 each) shifts the surface perpendicularly by a few
    eps32 * length, and a ray at grazing incidence turns that into 1/|cos θ| as much
    along the ray. Rays that need the grazing term are counted in ``grazing_t``.
    Two triangles are *tied* when the reference's second-closest distinct hit lies within
    the tolerance of its closest, or when they share a corner position and the
    reference hit is within ``tie_bary`` (smallest barycentric) of its triangle's edge;
    in either case our triangle, intersected in double, must be hit at a t within the
    tolerance and no further than ``tie_bary`` outside it. A disagreement is *grazing*
    when one side reports a hit (ours measured in double) within ``graze_bary`` of its
    triangle's edge and the other side does not see it: either a hit/miss disagreement,
    or both hit but the nearer of the two hits is such an edge contact (a ray exactly
    through a vertex or along a face may touch an edge the other intersector rounds away).
    Grazing disagreements are counted (``graze_mismatches``); callers bound them.
    """
    ours = scene.intersect(origins, directions, tmin, tmax)  # type: ignore[attr-defined]
    ref = native.reference_intersect(vertices, faces, origins, directions, tmin, tmax)
    n = origins.shape[0]
    t, prim, u, v = ours["t"], ours["prim"], ours["u"], ours["v"]
    hit, rhit = prim >= 0, ref["prim"] >= 0
    nonfinite = int(
        np.isnan(t).sum()
        + np.isnan(u).sum()
        + np.isnan(v).sum()
        + (np.isfinite(t) != hit).sum()
        + (hit & (prim >= faces.shape[0])).sum()
    )
    dlen = np.linalg.norm(directions, axis=1)
    # Incidence of each reference hit: float32 rounding moves the surface by a bounded
    # perpendicular amount, which a grazing ray turns into 1/|cos| times as much along it.
    cos = np.ones(n)
    r = np.flatnonzero(rhit)
    q = vertices[faces[ref["prim"][r]].astype(np.int64)]
    normal = np.cross(q[:, 1] - q[:, 0], q[:, 2] - q[:, 0])
    cos[r] = np.abs(np.einsum("ij,ij->i", normal, directions[r])) / (np.linalg.norm(normal, axis=1) * dlen[r])
    with np.errstate(invalid="ignore", over="ignore", divide="ignore"):
        plain = rel * np.maximum(ref["t"] * dlen, length) + abs_distance
        tol = (plain + grazing_eps * length / cos) / dlen  # in t units
        plain /= dlen

    # Our triangle in double, for every ray where we report one.
    idx = np.flatnonzero(hit)
    dt, du, dv = triangle_hits(vertices, faces, prim[idx], origins[idx], directions[idx])
    our_t = np.full(n, np.nan)
    our_bary = np.full(n, np.nan)
    our_t[idx], our_bary[idx] = dt, min_barycentric(du, dv)
    ref_bary = min_barycentric(ref["u"], ref["v"])

    mismatch = np.flatnonzero(hit != rhit)
    grazing = np.where(rhit[mismatch], ref_bary[mismatch], our_bary[mismatch]) < graze_bary
    grazing &= np.where(rhit[mismatch], True, np.abs(our_bary[mismatch]) < graze_bary)

    both = np.flatnonzero(hit & rhit)
    err = np.abs(t[both] - ref["t"][both])
    far = ~(err <= tol[both])
    diff = prim[both] != ref["prim"][both]
    db = both[diff]
    tie = np.zeros(len(both), dtype=bool)
    tie[diff] = (np.abs(ref["t_second"][db] - ref["t"][db]) <= tol[db]) | (
        share_a_vertex(vertices, faces, prim[db], ref["prim"][db]) & (ref_bary[db] < tie_bary)
    )
    tie &= (np.abs(our_t[both] - ref["t"][both]) <= tol[both]) & (our_bary[both] >= -tie_bary)
    # Different places or triangles, and the nearer hit is an edge contact the other
    # intersector rounded away: the same silhouette case as a hit/miss disagreement.
    nearer_ours = (
        (t[both] <= ref["t"][both] + tol[both])
        & (np.abs(our_bary[both]) < graze_bary)
        & (np.abs(our_t[both] - t[both]) <= tol[both])
    )
    nearer_ref = (ref["t"][both] <= t[both] + tol[both]) & (ref_bary[both] < graze_bary)
    edge_first = (far | (diff & ~tie)) & (nearer_ours | nearer_ref)
    bad_t = both[far & ~edge_first]
    bad_prims = both[diff & ~tie & ~edge_first & ~far]  # a t error is reported once, as such
    keep = ~edge_first
    both, err = both[keep], err[keep]
    grazing_t = int((err > plain[both]).sum())

    # Hit point from our barycentrics on our triangle against the reference point.
    good = np.setdiff1d(both, bad_t)
    p = vertices[faces[prim[good]].astype(np.int64)]
    uu, vv = u[good].astype(np.float64), v[good].astype(np.float64)
    ours_point = p[:, 0] * (1 - uu - vv)[:, None] + p[:, 1] * uu[:, None] + p[:, 2] * vv[:, None]
    ref_point = origins[good] + directions[good] * ref["t"][good][:, None]
    point_err = np.linalg.norm(ours_point - ref_point, axis=1) / (tol[good] * dlen[good])
    with np.errstate(divide="ignore", invalid="ignore"):
        rel_err = np.where(ref["t"][both] > 0, err / ref["t"][both], 0.0)

    return Agreement(
        rays=n,
        hits=int(hit.sum()),
        graze_mismatches=int(grazing.sum() + edge_first.sum()),
        bad_mismatches=mismatch[~grazing],
        ties=int((tie & keep).sum()),
        bad_prims=bad_prims,
        bad_t=bad_t,
        grazing_t=grazing_t,
        max_t_error=float((err / tol[both]).max(initial=0.0)),
        max_rel_t_error=float(rel_err.max(initial=0.0)),
        max_point_error=float(point_err.max(initial=0.0)),
        nonfinite=nonfinite,
    )


@pytest.fixture(scope="session")
def reference_check() -> Callable[..., Agreement]:
    """`compare_with_reference` (see its docstring for the tolerances and tie rules)."""
    return compare_with_reference
