"""Shared pieces of the procedural scenes: the chunk type and batched primitive builders.

Every builder takes arrays describing n primitives and returns one (vertices, faces)
pair for all of them, so a scene pays numpy's per-call overhead per batch of parts, not
per part. Triangles are wound counter-clockwise seen from outside.
"""

from __future__ import annotations

import math
from collections.abc import Iterator

import numpy as np

__all__ = [
    "CHUNK_TRIANGLES",
    "Chunk",
    "ChunkBuffer",
    "boxes",
    "cylinders",
    "drop_degenerate",
    "elbows",
    "golden_hues",
    "hsv_to_rgb",
    "signed_volume",
    "uv_sphere",
]

# (vertices float64 (k, 3), faces uint32 (m, 3) into this chunk's vertices,
#  face colours uint8 (m, 3) or None)
Chunk = tuple[np.ndarray, np.ndarray, np.ndarray | None]

# Upper bound on the triangles in one yielded chunk; with float64 vertices a full chunk
# is some tens of MB, which keeps generation of 10^8 triangles in bounded memory.
CHUNK_TRIANGLES = 1 << 20


class ChunkBuffer:
    """Collects parts and hands them out as chunks of at most ``limit`` triangles."""

    def __init__(self, limit: int | None = None, coloured: bool = True) -> None:
        # Read at construction, not import, so tests can shrink the module constant.
        self.limit = CHUNK_TRIANGLES if limit is None else limit
        self.coloured = coloured
        self._parts: list[tuple[np.ndarray, np.ndarray, np.ndarray | None]] = []
        self._triangles = 0

    @property
    def triangles(self) -> int:
        return self._triangles

    def add(self, vertices: np.ndarray, faces: np.ndarray, colours: np.ndarray | None) -> None:
        if faces.shape[0] == 0:
            return
        if self.coloured != (colours is not None):
            raise ValueError("a scene's parts must all have colours or all have none")
        self._parts.append((vertices, faces, colours))
        self._triangles += faces.shape[0]

    def full(self) -> bool:
        return self._triangles >= self.limit

    def drain(self, final: bool = False) -> Iterator[Chunk]:
        """Yield chunks of at most ``limit`` triangles; keep a partial tail unless final."""
        while self._parts and (final or self._triangles >= self.limit):
            taken: list[tuple[np.ndarray, np.ndarray, np.ndarray | None]] = []
            count = 0
            while self._parts and count + self._parts[0][1].shape[0] <= self.limit:
                part = self._parts.pop(0)
                taken.append(part)
                count += part[1].shape[0]
            if not taken:
                # One part larger than a chunk: split it by faces.
                vertices, faces, colours = self._parts.pop(0)
                hc = None if colours is None else colours[: self.limit]
                tc = None if colours is None else colours[self.limit :]
                self._parts.insert(0, (*_compact(vertices, faces[self.limit :]), tc))
                taken.append((*_compact(vertices, faces[: self.limit]), hc))
                count = taken[0][1].shape[0]
            self._triangles -= count
            yield _concat(taken)


def _compact(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    used, inverse = np.unique(faces, return_inverse=True)
    return vertices[used], inverse.reshape(-1, 3)


def _concat(parts: list[tuple[np.ndarray, np.ndarray, np.ndarray | None]]) -> Chunk:
    vertices: list[np.ndarray] = []
    faces: list[np.ndarray] = []
    offset = 0
    for v, f, _ in parts:
        vertices.append(v)
        faces.append(f.astype(np.int64) + offset)
        offset += v.shape[0]
    if offset >= 2**32:
        raise OverflowError("chunk has too many vertices for uint32 indices")
    colours = None
    if parts[0][2] is not None:
        colours = np.concatenate([c for _, _, c in parts]).astype(np.uint8, copy=False)
    return (
        np.concatenate(vertices).astype(np.float64, copy=False),
        np.concatenate(faces).astype(np.uint32),
        colours,
    )


def drop_degenerate(
    vertices: np.ndarray, faces: np.ndarray, colours: np.ndarray | None
) -> tuple[np.ndarray, np.ndarray | None]:
    """Remove zero-area triangles, so generated scenes pass ``validate`` silently."""
    a = vertices[faces[:, 0]]
    keep = np.cross(vertices[faces[:, 1]] - a, vertices[faces[:, 2]] - a).any(axis=1)
    if keep.all():
        return faces, colours
    return faces[keep], None if colours is None else colours[keep]


def _ring_faces(n_rings: int, m: int) -> np.ndarray:
    """Side faces joining ``n_rings`` consecutive rings of ``m`` vertices each."""
    j = np.arange(m)
    jn = (j + 1) % m
    quads = []
    for s in range(n_rings - 1):
        a0, a1 = s * m + j, s * m + jn
        b0, b1 = (s + 1) * m + j, (s + 1) * m + jn
        quads.append(np.stack([a0, a1, b1, a0, b1, b0], axis=1).reshape(-1, 3))
    return np.concatenate(quads)


def _fan(first: int, m: int, flip: bool) -> np.ndarray:
    j = np.arange(1, m - 1)
    tri = np.stack([np.full_like(j, first), first + j, first + j + 1], axis=1)
    return tri[:, ::-1].copy() if flip else tri


def _replicate(template_faces: np.ndarray, n: int, verts_each: int) -> np.ndarray:
    offsets = (np.arange(n, dtype=np.int64) * verts_each)[:, None, None]
    return (template_faces[None, :, :].astype(np.int64) + offsets).reshape(-1, 3)


def _perpendicular_frame(d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit u, v with (u, v, d) right-handed; axis-aligned whenever d is.

    Axis-aligned frames make rings of consecutive cylinders and elbows coincide as point
    sets (for m divisible by 4), so pipes show no seams at joints.
    """
    axis = np.argmax(np.abs(d), axis=1)
    e = np.zeros_like(d)
    e[np.arange(d.shape[0]), (axis + 1) % 3] = 1.0
    u = e - (e * d).sum(axis=1, keepdims=True) * d
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    v = np.cross(d, u)
    return u, v


def cylinders(
    p0: np.ndarray, p1: np.ndarray, radius: np.ndarray, m: int, caps: bool
) -> tuple[np.ndarray, np.ndarray]:
    """n cylinders from p0 to p1; 2m side triangles each, plus 2(m-2) with caps."""
    p0 = np.asarray(p0, dtype=np.float64).reshape(-1, 3)
    p1 = np.asarray(p1, dtype=np.float64).reshape(-1, 3)
    n = p0.shape[0]
    r = np.broadcast_to(np.asarray(radius, dtype=np.float64), (n,))[:, None, None]
    d = p1 - p0
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    u, v = _perpendicular_frame(d)
    theta = 2.0 * np.pi * np.arange(m) / m
    ring = np.cos(theta)[None, :, None] * u[:, None, :] + np.sin(theta)[None, :, None] * v[:, None, :]
    verts = np.concatenate([p0[:, None, :] + r * ring, p1[:, None, :] + r * ring], axis=1)
    template = _ring_faces(2, m)
    if caps:
        template = np.concatenate([template, _fan(0, m, flip=True), _fan(m, m, flip=False)])
    return verts.reshape(-1, 3), _replicate(template, n, 2 * m)


def elbows(
    center: np.ndarray,
    e1: np.ndarray,
    e2: np.ndarray,
    bend_radius: np.ndarray,
    radius: np.ndarray,
    m: int,
    k: int,
) -> tuple[np.ndarray, np.ndarray]:
    """n quarter-torus pipe bends, 2mk triangles each.

    The tube's centre line runs from ``center + R*e1`` to ``center + R*e2`` (e1 ⟂ e2,
    unit), so it joins a straight pipe along e2 at the start and one along e1 at the end.
    """
    center = np.asarray(center, dtype=np.float64).reshape(-1, 3)
    e1 = np.asarray(e1, dtype=np.float64).reshape(-1, 3)
    e2 = np.asarray(e2, dtype=np.float64).reshape(-1, 3)
    n = center.shape[0]
    big_r = np.broadcast_to(np.asarray(bend_radius, dtype=np.float64), (n,))
    small_r = np.broadcast_to(np.asarray(radius, dtype=np.float64), (n,))
    b = np.cross(e1, e2)
    alpha = (0.5 * np.pi * np.arange(k + 1) / k)[None, :, None]
    w = np.cos(alpha) * e1[:, None, :] + np.sin(alpha) * e2[:, None, :]  # (n, k+1, 3)
    spine = center[:, None, :] + big_r[:, None, None] * w
    theta = (2.0 * np.pi * np.arange(m) / m)[None, None, :, None]
    # (b, w) is right-handed about the direction of travel, so winding matches cylinders.
    ring = np.cos(theta) * b[:, None, None, :] + np.sin(theta) * w[:, :, None, :]
    verts = spine[:, :, None, :] + small_r[:, None, None, None] * ring
    return verts.reshape(-1, 3), _replicate(_ring_faces(k + 1, m), n, (k + 1) * m)


# Corner c of a box has offsets (c & 1, c >> 1 & 1, c >> 2 & 1) along x, y, z.
_BOX_FACES = np.array(
    [
        [0, 4, 6], [0, 6, 2],  # -x
        [1, 3, 7], [1, 7, 5],  # +x
        [0, 1, 5], [0, 5, 4],  # -y
        [2, 6, 7], [2, 7, 3],  # +y
        [0, 2, 3], [0, 3, 1],  # -z
        [4, 5, 7], [4, 7, 6],  # +z
    ],
    dtype=np.int64,
)  # fmt: skip
_BOX_CORNERS = np.array([[c & 1, (c >> 1) & 1, (c >> 2) & 1] for c in range(8)], dtype=bool)


def boxes(lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """n axis-aligned boxes, 12 triangles each."""
    lo = np.asarray(lo, dtype=np.float64).reshape(-1, 3)
    hi = np.asarray(hi, dtype=np.float64).reshape(-1, 3)
    verts = np.where(_BOX_CORNERS[None, :, :], hi[:, None, :], lo[:, None, :])
    return verts.reshape(-1, 3), _replicate(_BOX_FACES, lo.shape[0], 8)


def uv_sphere(n_lon: int, n_lat: int) -> tuple[np.ndarray, np.ndarray]:
    """Unit sphere with poles on ±y: 2 * n_lon * (n_lat - 1) triangles, none degenerate.

    Poles are single vertices joined by fans, which avoids the zero-area triangles a
    plain latitude-longitude grid has there.
    """
    phi = np.pi * np.arange(1, n_lat) / n_lat  # polar angle of the inner rings
    lam = 2.0 * np.pi * np.arange(n_lon) / n_lon
    sp, cp = np.sin(phi)[:, None], np.cos(phi)[:, None]
    rings = np.stack(
        [sp * np.cos(lam)[None, :], np.broadcast_to(cp, (n_lat - 1, n_lon)), -sp * np.sin(lam)],
        axis=-1,
    ).reshape(-1, 3)
    verts = np.concatenate([[[0.0, 1.0, 0.0]], rings, [[0.0, -1.0, 0.0]]])
    j = np.arange(n_lon)
    jn = (j + 1) % n_lon
    top = np.stack([np.zeros_like(j), 1 + j, 1 + jn], axis=1)
    south = verts.shape[0] - 1
    last = 1 + (n_lat - 2) * n_lon
    bottom = np.stack([np.full_like(j, south), last + jn, last + j], axis=1)
    parts = [top]
    if n_lat > 2:
        # Rings advance towards -y, against the handedness _ring_faces assumes.
        parts.append(_ring_faces(n_lat - 1, n_lon)[:, ::-1] + 1)
    parts.append(bottom)
    return verts, np.concatenate(parts)


def signed_volume(vertices: np.ndarray, faces: np.ndarray) -> float:
    """Signed volume of a closed mesh: positive when faces wind outward (used in tests)."""
    a, b, c = (vertices[faces[:, i]] for i in range(3))
    return float(np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6.0)


def hsv_to_rgb(h: np.ndarray, s: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Vectorised HSV (all in [0, 1]) to uint8 RGB."""
    h = np.asarray(h, dtype=np.float64) % 1.0
    i = np.floor(h * 6.0).astype(np.int64) % 6
    f = h * 6.0 - np.floor(h * 6.0)
    p, q, t = v * (1 - s), v * (1 - f * s), v * (1 - (1 - f) * s)
    table = np.stack(
        [
            np.stack([v, t, p], -1),
            np.stack([q, v, p], -1),
            np.stack([p, v, t], -1),
            np.stack([p, q, v], -1),
            np.stack([t, p, v], -1),
            np.stack([v, p, q], -1),
        ],
        axis=0,
    )
    rgb = table[i, np.arange(h.shape[0])]
    return np.clip(np.rint(rgb * 255.0), 0, 255).astype(np.uint8)


def golden_hues(n: int, start: float) -> np.ndarray:
    """Hues spread by the golden ratio, so neighbours in a sequence differ clearly."""
    return (start + np.arange(n) * (math.sqrt(5.0) - 1.0) / 2.0) % 1.0
