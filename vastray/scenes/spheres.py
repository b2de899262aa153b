"""``spheres``: coloured UV spheres resting on a checkered ground, y up.

The number of spheres grows as sqrt(N) (3 at 10^3 triangles, about 1250 at 10^8), and
each sphere's share of the budget is proportional to its surface area, so tessellation
looks uniform across sizes.
"""

from __future__ import annotations

import math
from collections.abc import Iterator

import numpy as np

from vastray.scenes._geom import Chunk, ChunkBuffer, hsv_to_rgb, uv_sphere

__all__ = ["spheres"]

_SPACING = 4.0  # grid pitch; radii stay below half of it so spheres never touch
_R_MIN, _R_MAX = 0.4, 1.6
_GROUND_COLOURS = np.array([[205, 205, 200], [150, 150, 145]], dtype=np.uint8)


def _tessellation(target: int) -> tuple[int, int]:
    """(n_lon, n_lat) whose 2 * n_lon * (n_lat - 1) triangles are closest to target."""
    q = max(1, round(math.sqrt(max(target, 6) / 4.0)))
    n_lon = max(3, round(target / (2.0 * q)))
    return n_lon, q + 1


def spheres(triangles: int, seed: int) -> Iterator[Chunk]:
    rng = np.random.default_rng([seed, 0x5F])
    n = max(3, round(math.sqrt(triangles) / 8.0))
    grid = math.ceil(math.sqrt(n))
    ground_tris = 2 * grid * grid
    budget = triangles - ground_tris

    radii = rng.uniform(_R_MIN, _R_MAX, n)
    cells = rng.permutation(grid * grid)[:n]
    slack = _SPACING / 2.0 - radii - 0.05
    centers = np.stack(
        [
            (cells % grid + 0.5) * _SPACING + rng.uniform(-1.0, 1.0, n) * slack,
            radii,
            (cells // grid + 0.5) * _SPACING + rng.uniform(-1.0, 1.0, n) * slack,
        ],
        axis=1,
    )
    colours = hsv_to_rgb(rng.random(n), rng.uniform(0.55, 0.95, n), rng.uniform(0.7, 1.0, n))

    out = ChunkBuffer()
    # Ground: one square tile (two triangles) per grid cell, alternating shades.
    gi, gj = np.meshgrid(np.arange(grid), np.arange(grid), indexing="ij")
    x0, z0 = gi.ravel() * _SPACING, gj.ravel() * _SPACING
    zeros = np.zeros_like(x0, dtype=np.float64)
    quad = np.stack(
        [
            np.stack([x0, zeros, z0], -1),
            np.stack([x0, zeros, z0 + _SPACING], -1),
            np.stack([x0 + _SPACING, zeros, z0 + _SPACING], -1),
            np.stack([x0 + _SPACING, zeros, z0], -1),
        ],
        axis=1,
    ).reshape(-1, 3)
    base = (np.arange(grid * grid) * 4)[:, None]
    tiles = np.concatenate([base + np.array([0, 1, 2]), base + np.array([0, 2, 3])], axis=1)
    tiles = tiles.reshape(-1, 3)
    shade = _GROUND_COLOURS[(gi.ravel() + gj.ravel()) % 2]
    out.add(quad, tiles, np.repeat(shade, 2, axis=0))

    # Each sphere aims at the ideal cumulative count so rounding errors do not add up.
    weights = np.cumsum(radii**2) / np.sum(radii**2)
    made = 0
    for i in range(n):
        # Nearly every sphere has its own tessellation, so templates are not cached
        # (a cache would grow with the sphere count).
        unit, faces = uv_sphere(*_tessellation(round(budget * weights[i]) - made))
        out.add(unit * radii[i] + centers[i], faces, np.tile(colours[i], (faces.shape[0], 1)))
        made += faces.shape[0]
        yield from out.drain()
    yield from out.drain(final=True)
