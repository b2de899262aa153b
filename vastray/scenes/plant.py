"""``plant``: a CAD-like process plant, y up, in metres.

The plant is a grid of modules (about 250k triangles each, one chunk per module, each
with its own random stream so the output does not depend on chunking). A module is a
steel frame of H-section columns and I-beams with a few grating floors, some vertical
vessels and equipment skids, and many thin pipes. Pipes follow axis-aligned routes on
a 1 m lattice; an occupancy grid keeps them from crossing each other or the steel, so
the model stays clean to trace (no intersecting solids along a pipe). Bends are quarter
tori, pipe ends and some joints carry flanges with hex bolts, some joints carry valves
with hand wheels, and horizontal runs rest on small support shoes. Colours follow the
pipe's system, as on real plant drawings.

Bigger budgets mean more (and bigger) modules; tessellation rises modestly with size
(8 segments around a pipe up to 2*10^6 triangles, 12 up to 3*10^7, then 16).
"""

from __future__ import annotations

import itertools
import math
from collections import defaultdict
from collections.abc import Iterator

import numpy as np

from vastray.scenes._geom import Chunk, ChunkBuffer, boxes, cylinders, elbows

__all__ = ["MODULE_TRIANGLES", "PART_NAMES", "part_of_colours", "plant"]

MODULE_TRIANGLES = 250_000
_STEP = 1.0  # lattice pitch (m)
_BAY = 6  # lattice steps between column rows
_LEVEL = 5  # lattice steps between floors

# Colours of pipe systems (steam, cooling water, fuel gas, instrument air, lube oil,
# process chemicals, fire water) and of the rest of the plant.
_SYSTEMS = np.array(
    [
        [196, 52, 40],
        [46, 139, 87],
        [228, 186, 40],
        [70, 130, 200],
        [130, 86, 46],
        [148, 78, 160],
        [232, 118, 34],
    ],
    dtype=np.float64,
)
_STEEL = (96, 108, 124)
_GRATING = (84, 86, 84)
_CONCRETE = (168, 166, 158)
_VESSEL = (214, 214, 208)
_SKID = (50, 100, 150)
_BOLT = (48, 48, 52)
_SHOE = (128, 128, 128)
_WHEEL = (180, 30, 30)

# The plant's parts, as a plant's design review knows them: a pipe system or a kind of
# structure, across all modules (what "highlight the fuel gas system" finds).
PART_NAMES = (
    "steam pipes",
    "cooling water pipes",
    "fuel gas pipes",
    "instrument air pipes",
    "lube oil pipes",
    "process chemical pipes",
    "fire water pipes",
    "steel frame",
    "gratings",
    "concrete slabs",
    "vessels",
    "equipment skids",
    "bolts",
    "pipe supports",
    "valve hand wheels",
)
_FIXED = (_STEEL, _GRATING, _CONCRETE, _VESSEL, _SKID, _BOLT, _SHOE, _WHEEL)


def part_of_colours(colours: np.ndarray) -> np.ndarray:
    """The part (an index of PART_NAMES) of each triangle from its colour: the structure
    colours are fixed; a pipe's colour (and its flanges' darker one) is its system's,
    scaled, so the system is the one whose colour points the same way."""
    rgb = np.asarray(colours, dtype=np.float64).reshape(-1, 3)
    unit = _SYSTEMS / np.linalg.norm(_SYSTEMS, axis=1, keepdims=True)
    out = np.argmax(rgb @ unit.T, axis=1).astype(np.uint32)
    for k, fixed in enumerate(_FIXED):
        out[np.all(rgb == fixed, axis=1)] = len(_SYSTEMS) + k
    return out


_RADII = np.array([0.025, 0.04, 0.06, 0.09, 0.13, 0.18, 0.25])
_RADII_P = np.array([0.2, 0.22, 0.2, 0.15, 0.11, 0.08, 0.04])
_AXES = np.eye(3, dtype=np.int64)
RGB = tuple[int, int, int]
Vec = np.ndarray  # (3,) float64 point or direction
_UNIT = np.eye(3)


def _segments_around(triangles: int) -> int:
    if triangles <= 2_000_000:
        return 8
    if triangles <= 30_000_000:
        return 12
    return 16


class _Parts:
    """Primitive descriptions of one module, built into arrays in a few batched calls."""

    def __init__(self, m: int) -> None:
        self.m = m
        self.cyl: dict[tuple[int, bool], list[tuple[Vec, Vec, float, RGB]]] = defaultdict(list)
        self.elb: dict[tuple[int, int], list[tuple[Vec, Vec, Vec, float, float, RGB]]] = defaultdict(list)
        self.box: list[tuple[Vec, Vec, RGB]] = []
        self.triangles = 0

    def cylinder(
        self, p0: Vec, p1: Vec, r: float, colour: RGB, m: int | None = None, caps: bool = False
    ) -> None:
        m = self.m if m is None else m
        self.cyl[(m, caps)].append((p0, p1, r, colour))
        self.triangles += 2 * m + (2 * (m - 2) if caps else 0)

    def elbow(
        self, c: Vec, e1: Vec, e2: Vec, bend: float, r: float, colour: RGB, m: int | None = None
    ) -> None:
        m = self.m if m is None else m
        k = max(2, m // 2)  # sections per quarter bend, so bends look as round as pipes
        self.elb[(m, k)].append((c, e1, e2, bend, r, colour))
        self.triangles += 2 * m * k

    def cuboid(self, lo: Vec, hi: Vec, colour: RGB) -> None:
        self.box.append((lo, hi, colour))
        self.triangles += 12

    def merge(self, other: _Parts) -> None:
        for key, items in other.cyl.items():
            self.cyl[key].extend(items)
        for key, items in other.elb.items():
            self.elb[key].extend(items)
        self.box.extend(other.box)
        self.triangles += other.triangles

    def build(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        verts, faces, colours = [], [], []
        offset = 0

        def put(v: np.ndarray, f: np.ndarray, rgb: np.ndarray, per: int) -> None:
            nonlocal offset
            verts.append(v)
            faces.append(f + offset)
            colours.append(np.repeat(np.asarray(rgb, dtype=np.uint8), per, axis=0))
            offset += v.shape[0]

        for (m, caps), items in sorted(self.cyl.items()):
            p0, p1, r, rgb = (np.array(x) for x in zip(*items, strict=True))
            v, f = cylinders(p0, p1, r, m, caps)
            put(v, f, rgb, f.shape[0] // len(items))
        for (m, k), items in sorted(self.elb.items()):
            c, e1, e2, bend, r, rgb = (np.array(x) for x in zip(*items, strict=True))
            v, f = elbows(c, e1, e2, bend, r, m, k)
            put(v, f, rgb, f.shape[0] // len(items))
        if self.box:
            lo, hi, rgb = (np.array(x) for x in zip(*self.box, strict=True))
            v, f = boxes(lo, hi)
            put(v, f, rgb, 12)
        return np.concatenate(verts), np.concatenate(faces), np.concatenate(colours)


class _Module:
    def __init__(
        self,
        rng: np.random.Generator,
        cells: tuple[int, int, int],
        origin: np.ndarray,
        m: int,
        far_x: bool,
        far_z: bool,
    ) -> None:
        self.rng = rng
        self.nx, self.ny, self.nz = cells
        self.origin = origin
        self.m = m
        # Lattice points taken by steel, equipment or pipes; the border planes belong
        # to no pipe so neighbouring modules cannot collide.
        self.occ = np.zeros((self.nx + 1, self.ny + 1, self.nz + 1), dtype=bool)
        self.occ[0, :, :] = self.occ[-1, :, :] = True
        self.occ[:, :, 0] = self.occ[:, :, -1] = True
        self.occ[:, 0, :] = True
        self.rows_x = list(range(0, self.nx + (1 if far_x else 0), _BAY))
        self.rows_z = list(range(0, self.nz + (1 if far_z else 0), _BAY))
        self.levels = list(range(_LEVEL, self.ny + 1, _LEVEL))
        self.parts = _Parts(m)
        self.runs: list[tuple[np.ndarray, np.ndarray, float]] = []  # horizontal pipe runs

    def world(self, p: Vec | tuple[float, float, float]) -> np.ndarray:
        return self.origin + np.asarray(p, dtype=np.float64) * _STEP

    # -- steel and equipment -------------------------------------------------------
    def _h_section(self, p0: np.ndarray, p1: np.ndarray, axis: int, depth: float) -> None:
        """I-beam (or H-column) from p0 to p1 along ``axis``: two flanges and a web."""
        t, width = 0.025 * depth / 0.3 + 0.01, 0.65 * depth
        web_axis = 1 if axis != 1 else 0  # beams stand upright, columns face x
        side = 3 - axis - web_axis
        lo, hi = np.minimum(p0, p1), np.maximum(p0, p1)
        half = np.zeros(3)
        half[web_axis] = depth / 2
        for sign in (-1.0, 1.0):
            a, b = lo.copy(), hi.copy()
            a[web_axis] += sign * half[web_axis] - (t if sign > 0 else 0)
            b[web_axis] = a[web_axis] + t
            a[side] -= width / 2
            b[side] += width / 2
            self.parts.cuboid(a, b, _STEEL)
        a, b = lo.copy(), hi.copy()
        a[web_axis] -= depth / 2 - t
        b[web_axis] += depth / 2 - t
        a[side] -= t / 2
        b[side] += t / 2
        self.parts.cuboid(a, b, _STEEL)

    def steel(self) -> None:
        nx, ny, nz = self.nx, self.ny, self.nz
        top = ny * _STEP
        slab_lo = self.world((0, 0, 0)) - np.array([0.0, 0.3, 0.0])
        self.parts.cuboid(slab_lo, self.world((nx, 0, nz)), _CONCRETE)
        col_half = 0.18
        for i in self.rows_x:
            for k in self.rows_z:
                base = self.world((i, 0, k))
                self._h_section(base, base + np.array([0.0, top + 0.15, 0.0]), 1, 0.3)
                self.occ[i, :, k] = True
        for j in self.levels:
            for k in self.rows_z:
                for i0 in range(0, nx, _BAY):
                    p0 = self.world((i0, j, k)) + np.array([col_half, 0.0, 0.0])
                    p1 = self.world((min(i0 + _BAY, nx), j, k)) - np.array([col_half, 0.0, 0.0])
                    self._h_section(p0, p1, 0, 0.25)
                self.occ[:, j, k] = True
            for i in self.rows_x:
                for k0 in range(0, nz, _BAY):
                    p0 = self.world((i, j, k0)) + np.array([0.0, 0.0, col_half])
                    p1 = self.world((i, j, min(k0 + _BAY, nz))) - np.array([0.0, 0.0, col_half])
                    self._h_section(p0, p1, 2, 0.25)
                self.occ[i, j, :] = True

    def equipment(self) -> None:
        rng = self.rng
        bays = [(i, k) for i in range(0, self.nx, _BAY) for k in range(0, self.nz, _BAY)]
        for i0, k0 in bays:
            roll = rng.random()
            if roll < 0.12 and self.ny >= 4:
                self._vessel(i0, k0)
            elif roll < 0.3:
                self._skid(i0, k0)
        for j in self.levels[:-1] if len(self.levels) > 1 else self.levels:
            for i0, k0 in bays:
                if rng.random() < 0.18:
                    self._grating(i0, j, k0)

    def _vessel(self, i0: int, k0: int) -> None:
        rng = self.rng
        radius = rng.uniform(0.8, 2.2)
        height = int(rng.integers(3, self.ny))
        ci, ck = i0 + _BAY / 2, k0 + _BAY / 2
        i, j, k = np.ogrid[: self.nx + 1, : self.ny + 1, : self.nz + 1]
        near = ((i - ci) ** 2 + (k - ck) ** 2 <= (radius + 0.6) ** 2) & (j <= height + 1)
        self.occ |= near
        base = self.world((ci, 0, ck))
        self.parts.cylinder(
            base, base + np.array([0.0, height * _STEP, 0.0]), radius, _VESSEL, 4 * self.m, True
        )
        # A nozzle ring on top makes the vessel read as equipment, not as a post.
        ring = base + np.array([0.0, height * _STEP, 0.0])
        self.parts.cylinder(ring, ring + np.array([0.0, 0.25, 0.0]), 0.3, _VESSEL, self.m, True)

    def _skid(self, i0: int, k0: int) -> None:
        rng = self.rng
        size = np.array([rng.uniform(1.0, 2.5), rng.uniform(0.6, 1.6), rng.uniform(0.8, 2.0)])
        lo_i = i0 + rng.uniform(1.0, _BAY - 1.0 - size[0])
        lo_k = k0 + rng.uniform(1.0, _BAY - 1.0 - size[2])
        lo = np.array([lo_i, 0.0, lo_k])
        hi = lo + size
        self.parts.cuboid(self.world(lo), self.world(hi), _SKID)
        a = np.floor(lo - 0.5).astype(int).clip(0)
        b = np.ceil(hi + 0.5).astype(int)
        self.occ[a[0] : b[0] + 1, : b[1] + 1, a[2] : b[2] + 1] = True

    def _grating(self, i0: int, j: int, k0: int) -> None:
        i1, k1 = min(i0 + _BAY, self.nx), min(k0 + _BAY, self.nz)
        region = self.occ[i0 + 1 : i1, j, k0 + 1 : k1]
        if region.any():
            return  # a vessel already passes through this floor
        lo = self.world((i0, j, k0)) + np.array([0.1, 0.125, 0.1])
        hi = self.world((i1, j, k1)) + np.array([-0.1, 0.165, -0.1])
        self.parts.cuboid(lo, hi, _GRATING)
        self.occ[i0 : i1 + 1, j, k0 : k1 + 1] = True

    # -- pipes -------------------------------------------------------------------------
    def _free(self, q: np.ndarray) -> bool:
        return (
            bool(1 <= q[0] < self.nx and 1 <= q[1] <= self.ny and 1 <= q[2] < self.nz)
            and not self.occ[q[0], q[1], q[2]]
        )

    def _route(self) -> list[np.ndarray] | None:
        """Corners of a new route, marked as taken; None when no free start is found."""
        rng = self.rng
        for _ in range(20):
            p = np.array([rng.integers(1, self.nx), rng.integers(1, self.ny + 1), rng.integers(1, self.nz)])
            if not self.occ[p[0], p[1], p[2]]:
                break
        else:
            return None
        self.occ[p[0], p[1], p[2]] = True
        corners = [p]
        prev = -1
        for _ in range(int(rng.integers(2, 9))):
            options = [a for a in (0, 1, 2) if a != prev]
            weights = np.array([2.0 if a != 1 else 1.0 for a in options])
            order = rng.choice(options, size=len(options), replace=False, p=weights / weights.sum())
            moved = False
            for axis in order:
                for sign in rng.permutation([-1, 1]):
                    step = _AXES[axis] * sign
                    want = int(rng.integers(2, 14))
                    n = 0
                    while n < want and self._free(corners[-1] + step * (n + 1)):
                        n += 1
                    if n >= 2:
                        for t in range(1, n + 1):
                            q = corners[-1] + step * t
                            self.occ[q[0], q[1], q[2]] = True
                        corners.append(corners[-1] + step * n)
                        prev = int(axis)
                        moved = True
                        break
                if moved:
                    break
            if not moved:
                break
        return corners

    def _flange(
        self, parts: _Parts, at: np.ndarray, d: np.ndarray, r: float, colour: RGB, pair: bool
    ) -> None:
        """Flange(s) centred on ``at`` along unit ``d``; a pair is two faces bolted together."""
        rf = min(1.8 * r + 0.02, 0.46)
        tf = max(0.35 * r, 0.02)
        span = 2 * tf if pair else tf
        a, b = at - d * span / 2, at + d * span / 2
        if pair:
            parts.cylinder(a, at, rf, colour, caps=True)
            parts.cylinder(at, b, rf, colour, caps=True)
        else:
            parts.cylinder(a, b, rf, colour, caps=True)
        n_bolts = 4 if r < 0.13 else 8
        axis = int(np.argmax(np.abs(d)))
        u, v = _UNIT[(axis + 1) % 3], _UNIT[(axis + 2) % 3]
        pitch = (r + rf) / 2
        rb = max((rf - r) * 0.16, 0.004)
        for q in range(n_bolts):
            ang = (q + 0.5) * 2 * math.pi / n_bolts
            c = (math.cos(ang) * u + math.sin(ang) * v) * pitch
            parts.cylinder(a + c - d * 0.4 * tf, b + c + d * 0.4 * tf, rb, _BOLT, 6, True)

    def _valve(self, parts: _Parts, at: np.ndarray, d: np.ndarray, r: float, colour: RGB) -> None:
        axis = int(np.argmax(np.abs(d)))
        stem = _UNIT[1] if axis != 1 else _UNIT[0]
        body = np.full(3, 1.3 * r + 0.02)
        body[axis] = 1.8 * r + 0.04
        parts.cuboid(at - body, at + body, colour)
        top = at + stem * (3.0 * r + 0.15)
        parts.cylinder(at + stem * body.min(), top, max(0.12 * r, 0.008), _BOLT, 6, True)
        wheel, rim = 1.6 * r + 0.05, max(0.12 * r, 0.008)
        u = np.cross(stem, _UNIT[2])  # the stem is never along z
        w = np.cross(stem, u)
        for e1, e2 in ((u, w), (w, -u), (-u, -w), (-w, u)):
            parts.elbow(top, e1, e2, wheel, rim, _WHEEL, m=6)

    def pipe(self, budget_left: int) -> int | None:
        """Route and add one pipe if it fits; returns its triangles (None: no room)."""
        corners = self._route()
        if corners is None:
            return None
        if len(corners) < 2:
            return 0
        rng = self.rng
        r = float(rng.choice(_RADII, p=_RADII_P))
        system = _SYSTEMS[rng.integers(len(_SYSTEMS))]
        red, green, blue = (int(c) for c in np.clip(system * rng.uniform(0.85, 1.1), 0, 255))
        colour: RGB = (red, green, blue)
        dark: RGB = (int(red * 0.62), int(green * 0.62), int(blue * 0.62))
        bend = min(3.0 * r, 0.45 * _STEP)
        pts = [self.world(c) for c in corners]
        dirs = [(b - a) / np.linalg.norm(b - a) for a, b in itertools.pairwise(pts)]
        parts = _Parts(self.m)
        runs = []
        for s, (a, b) in enumerate(itertools.pairwise(pts)):
            d = dirs[s]
            start = a + d * bend if s > 0 else a
            end = b - d * bend if s < len(dirs) - 1 else b
            steps = round(float(np.linalg.norm(b - a)) / _STEP)
            fitting = None
            if steps >= 4 and rng.random() < 0.25:
                fitting = a + d * _STEP * (steps // 2)
            if fitting is not None and rng.random() < 0.4:
                self._valve(parts, fitting, d, r, dark)
            elif fitting is not None:
                self._flange(parts, fitting, d, r, dark, pair=True)
            parts.cylinder(start, end, r, colour)
            if abs(d[1]) < 0.5:
                runs.append((start, end, r))
        for s in range(1, len(pts) - 1):
            d_in, d_out = dirs[s - 1], dirs[s]
            centre = pts[s] - d_in * bend + d_out * bend
            parts.elbow(centre, -d_out, d_in, bend, r, colour)
        tf = max(0.35 * r, 0.02)
        self._flange(parts, pts[0] + dirs[0] * tf / 2, dirs[0], r, dark, pair=False)
        self._flange(parts, pts[-1] - dirs[-1] * tf / 2, dirs[-1], r, dark, pair=False)
        if parts.triangles > budget_left:
            return 0
        self.parts.merge(parts)
        self.runs.extend(runs)
        return parts.triangles

    def fill(self, triangles: int) -> None:
        """Spend the last triangles on support shoes under pipes (or cleats on beams)."""
        rng = self.rng
        for _ in range(triangles // 12):
            if self.runs:
                a, b, r = self.runs[int(rng.integers(len(self.runs)))]
                c = a + (b - a) * rng.uniform(0.15, 0.85)
                d = (b - a) / np.linalg.norm(b - a)
                across = np.cross(d, _UNIT[1])
                half = np.abs(d) * (0.6 * r + 0.02) + np.abs(across) * (0.8 * r + 0.02)
                lo = c - half - np.array([0.0, r + 0.12, 0.0])
                hi = c + half - np.array([0.0, r, 0.0])
                self.parts.cuboid(lo, hi, _SHOE)
            else:
                i = self.rows_x[int(rng.integers(len(self.rows_x)))]
                j = self.levels[int(rng.integers(len(self.levels)))] if self.levels else self.ny
                k = rng.uniform(0.5, self.nz - 0.5)
                c = self.world((i, j, k))
                self.parts.cuboid(c + np.array([-0.1, 0.125, -0.08]), c + np.array([0.1, 0.14, 0.08]), _SHOE)


def _module_cells(budget: int) -> tuple[int, int, int]:
    """Lattice size of a module so that pipes fill roughly a sixth of its points."""
    points = budget / 6.0
    levels = 1 if budget < 5_000 else 2 if budget < 30_000 else 3 if budget < 100_000 else 4
    ny = _LEVEL * levels
    bays = max(1, round(math.sqrt(points / ny) / _BAY))
    return _BAY * bays, ny, _BAY * bays


def plant(triangles: int, seed: int) -> Iterator[Chunk]:
    m = _segments_around(triangles)
    n_modules = math.ceil(triangles / MODULE_TRIANGLES)
    budgets = [triangles // n_modules + (1 if i < triangles % n_modules else 0) for i in range(n_modules)]
    cells = _module_cells(max(budgets))
    gx = math.ceil(math.sqrt(n_modules))
    gz = math.ceil(n_modules / gx)
    size = np.array([cells[0], 0, cells[2]], dtype=np.float64) * _STEP
    centre = np.array([gx, 0, gz]) * size / 2
    out = ChunkBuffer()
    for idx, budget in enumerate(budgets):
        a, b = idx % gx, idx // gx
        module = _Module(
            np.random.default_rng([seed, 0x9A7, idx]),
            cells,
            np.array([a, 0, b]) * size - centre,
            m,
            far_x=a == gx - 1 or idx + 1 >= n_modules,
            far_z=idx + gx >= n_modules,
        )
        module.steel()
        module.equipment()
        failures = 0
        while failures < 40:
            left = budget - module.parts.triangles
            made = module.pipe(left)
            if made is None:
                break
            failures = failures + 1 if made == 0 else 0
        module.fill(budget - module.parts.triangles)
        out.add(*module.parts.build())
        yield from out.drain()
    yield from out.drain(final=True)
