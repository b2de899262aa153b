"""Why rays reach triangle leaves: the LOD cut of one view, read from the file.

For the overview camera of a model (bench/tradeoff.py's: frame_bounds, 45 degrees) and a
pixels-of-error value this walks the kd-tree from the root the way a ray would decide
(paper 000's test, lod_traverse.h: a LOD node's voxel stands in once its enclosing
radius R <= t * PoE * pixel_angle / 2), with t the nearest distance from the eye to the
node's cell, which is the smallest t any ray entering the cell can have. It stops at
every LOD node that passes (the cut) and counts what lies below no passing node: the
triangle leaves that some ray may have to open at this PoE, and the triangle blocks
holding them. Occlusion is ignored, so this is an upper bound on the triangle part of
the working set, and a lower bound on nothing; it says *which* leaves escape the LOD.

For every escaping leaf it records the radius of the deepest LOD node above it (the
last voxel a ray passes), the leaf cell's extents (longest and shortest side), its
triangle count and its depth below that LOD node. Walking all of a 10^8 model in Python
is slow, so --region keeps the walk to the cells that meet a box of that fraction of
the model's extent (x and z) around its centre, and the counts are scaled up.

    python bench/lodcut.py bench/.cache/plant-1e8.vast --poe 2 --region 0.05
"""

from __future__ import annotations

import argparse
import math
import statistics
import struct
import sys
import time
from collections import Counter
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

from modelwalk import INNER, LEFT_EMPTY, LOD, RIGHT_EMPTY, SPLIT_STEPS, Walker, dequantize

from vastray.camera import frame_bounds
from vastray.modelfile import ModelFile


def box_distance(eye: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> float:
    return float(np.linalg.norm(np.maximum(0.0, np.maximum(lo - eye, eye - hi))))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("model", type=Path)
    ap.add_argument("--poe", type=float, default=2.0)
    ap.add_argument("--image", default="1280x720")
    ap.add_argument("--region", type=float, default=1.0, help="fraction of the x and z extent walked")
    args = ap.parse_args()
    width, height = (int(v) for v in args.image.split("x"))

    with ModelFile(args.model) as f:
        h = f.header
        centre = np.array(h["centre"], dtype=np.float64) if "centre" in h else np.zeros(3)
        lo_w, hi_w = (np.asarray(v, dtype=np.float64) for v in f.bounds)
        cam = frame_bounds(lo_w, hi_w, width=width, height=height)
        eye = np.asarray(cam.eye, dtype=np.float64) - centre  # cells are relative to the centre
        pixel_angle = 2.0 * math.tan(math.radians(cam.fov) / 2.0) / height
        cone = 0.5 * args.poe * pixel_angle
        mid = (lo_w + hi_w) / 2 - centre
        half = (hi_w - lo_w) / 2 * args.region
        r_lo, r_hi = mid - half, mid + half
        r_lo[1], r_hi[1] = -np.inf, np.inf

        walker = Walker(f)
        tri_level = walker.tri_level
        t0 = time.perf_counter()
        # (level, global block, off, depth, lo, hi, last LOD radius, kd depth below it)
        root_lo, root_hi = np.array(h["cell_lo"], np.float32), np.array(h["cell_hi"], np.float32)
        stack = [(0, 0, 0, 0, root_lo, root_hi, math.inf, 0, math.inf)]
        cut: Counter[str] = Counter()
        voxel_levels: Counter[int] = Counter()  # LOD level of the treelet holding each
        leaf_levels: Counter[int] = Counter()
        escaping: list[tuple[float, ...]] = []
        blocks: set[int] = set()
        lod_blocks: set[int] = set()
        while stack:
            level, block, off, depth, lo, hi, last_r, below, parent_r = stack.pop()
            if np.any(hi < r_lo) or np.any(lo > r_hi):
                continue
            data = walker.read(block)
            lod_blocks.add(block)
            w, w1 = struct.unpack_from("<II", data, off)
            if not w & INNER:
                count = (w >> 16) & 0x7FFF
                if count == 0:  # reads no block (its reference is not read)
                    continue
                tri_block = walker.resolve(tri_level, w1)[1]
                ext = np.sort(hi.astype(np.float64) - lo.astype(np.float64))
                t = box_distance(eye, lo, hi)
                leaf_r = 0.5 * float(np.linalg.norm(ext))
                row = (
                    last_r,
                    t * cone,
                    float(ext[2]),
                    float(ext[0]),
                    count,
                    below,
                    parent_r,
                    leaf_r,
                    tri_block,
                )
                escaping.append(row)
                # a leaf too big for one block continues in the next ones; count its first
                blocks.add(tri_block)
                cut["leaf"] += 1
                leaf_levels[level] += 1
                continue
            axis = w & 3
            small = f.quantized_splits and not w & LOD  # a 4-byte basic node (FORMAT.md §8)
            if small:
                split = dequantize(lo[axis], hi[axis], (w >> 10) & (SPLIT_STEPS - 1))
            else:
                split = struct.unpack("<f", struct.pack("<I", w1))[0]
            has_l, has_r = not w & LEFT_EMPTY, not w & RIGHT_EMPTY
            if w & LOD:
                if f.quantized_splits:  # a 12-byte LOD node: the radius is half the cell's diagonal
                    ext = (hi - lo).astype(np.float32)
                    radius = float(np.float32(0.5) * np.sqrt(np.float32(ext @ ext)))
                else:
                    radius = struct.unpack_from("<f", data, off + 8)[0]
                t = box_distance(eye, lo, hi)
                if radius <= t * cone:
                    cut["voxel"] += 1
                    voxel_levels[level] += 1
                    continue
                if level + 1 >= tri_level:
                    raise SystemExit("LOD node in the last node level")
                child_at = off + (8 if f.quantized_splits else 12)
                child_level = level + 1
                child_block = walker.resolve(child_level, struct.unpack_from("<I", data, child_at)[0])[1]
                l_off = 8 * ((w >> 17) & 8191)
                r_off = l_off + 8 * ((w >> 11) & 63) if has_l else l_off
                child_depth, last_r, below = 0, radius, 0
            else:
                child_level, child_block, child_depth = level, block, depth + 1
                size = 4 if small else 8
                l_off = off + size
                r_off = off + size * ((w >> 4) & 63) if has_l else off + size
            for side, present, coff in ((1, has_r, r_off), (0, has_l, l_off)):
                if present:
                    clo, chi = lo.copy(), hi.copy()
                    (chi if side == 0 else clo)[axis] = np.float32(split)
                    here_r = 0.5 * float(np.linalg.norm(hi.astype(np.float64) - lo.astype(np.float64)))
                    entry = (child_level, child_block, coff, child_depth, clo, chi, last_r, below + 1, here_r)
                    stack.append(entry)
        seconds = time.perf_counter() - t0

    scale = 1.0 / (args.region * args.region)
    n = len(escaping)
    print(
        f"model {args.model.name}: {width}x{height}, PoE {args.poe:g}, region {args.region:g} "
        f"(x{scale:.0f} to the whole), walked in {seconds:.1f} s"
    )
    print(
        f"  eye distance to centre {np.linalg.norm(eye - mid):.1f}, footprint cone {cone:.3g} "
        f"(R allowed at the centre: {np.linalg.norm(eye - mid) * cone:.3f})"
    )
    print(
        f"  cut: {cut['voxel']} voxels stand in, {n} leaves escape; triangle blocks with escaping "
        f"leaves {len(blocks)} (x scale ~{len(blocks) * scale:.0f}), node blocks walked {len(lod_blocks)}"
    )
    print(f"  LOD levels of the voxels that stand in: {dict(sorted(voxel_levels.items()))}")
    print(f"  LOD levels of the escaping leaves: {dict(sorted(leaf_levels.items()))}")
    if not n:
        return 0
    arr = np.array(escaping)
    ratio = arr[:, 0] / arr[:, 1]  # last voxel radius / allowed radius
    longest, shortest = arr[:, 2], arr[:, 3]
    allowed = arr[:, 1]
    q = lambda a: " / ".join(f"{v:.3g}" for v in np.percentile(a, [10, 50, 90]))  # noqa: E731
    print(f"  escaping leaves: last voxel R / allowed R  p10/p50/p90: {q(ratio)}")
    print(f"  leaf cell longest side / allowed diameter:  {q(longest / (2 * allowed))}")
    print(f"  leaf cell shortest side / allowed diameter: {q(shortest / (2 * allowed))}")
    print(f"  leaf triangles: {q(arr[:, 4])}; kd levels below the last LOD node: {q(arr[:, 5])}")
    small = longest <= 2 * allowed
    print(
        f"  leaves whose own cell would pass the test (longest side <= allowed diameter): "
        f"{100 * small.mean():.1f}%; of those, last voxel R / allowed median "
        f"{statistics.median(ratio[small]) if small.any() else math.nan:.3g}"
    )
    # What finer LOD would leave: a voxel at every inner node (the parent of a leaf is
    # the smallest cell above it), and a voxel for every leaf's own cell as well.
    for label, covered in (
        ("a voxel at every inner node", arr[:, 6] <= allowed),
        ("a voxel at every inner node and leaf", np.minimum(arr[:, 6], arr[:, 7]) <= allowed),
    ):
        left = {int(b) for b, c in zip(arr[:, 8], covered, strict=True) if not c}
        print(f"  with {label}: {100 * covered.mean():.1f}% of these leaves covered, triangle blocks "
              f"still needed {len(left)} of {len(blocks)}")  # fmt: skip
    thin = shortest <= 2 * allowed
    print(f"  leaves thinner than the allowed diameter on their shortest side: {100 * thin.mean():.1f}%")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
