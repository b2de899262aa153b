"""Cold open -> complete view: render_complete before and after issue 12's loading work.

For each model size (bench/tradeoff.py's plant models in bench/.cache) and each pixels of
error, the page cache is dropped, the model opened in a fresh cache and the 1280x720
overview rendered until complete in four ways, one after the other, so all see the
same machine: *before* (full frames from the start, fetches strictly by priority),
*discovery* (render_complete's coarse discovery frames first: vastray/outofcore.py
DISCOVERY_SCALE), *discovery + file order* (also fetching requests of about equal
priority in file order: BlockCache file_order, the default), and *+ read-ahead* (the
queued blocks handed to the kernel to read ahead: BlockCache readahead, the default;
the other three go without). The final images are
compared (they must be equal: all only change what is loaded when). Also measures the
disk's cold read rate of the model file: the bytes a view needs over it are the floor
of any cold start.

    python bench/complete.py --sizes 1e7,1e8 --poes 2 --repeats 2
"""

from __future__ import annotations

import argparse
import math
import os
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from common import RESULTS_DIR, markdown_table
from tradeoff import built_model, isa_path

from vastray import native, outofcore
from vastray.camera import frame_bounds
from vastray.outofcore import OutOfCoreModel
from vastray.pagecache import drop_page_cache  # fsync, then POSIX_FADV_DONTNEED
from vastray.units import parse_bytes


def cold_read_rate(path: Path, limit: int = 1 << 30) -> float:
    """MB/s of 64 KiB preads in file order from a dropped page cache (the fetchers' reads
    are 64 KiB blocks, mostly in file order within a level)."""
    drop_page_cache(path)
    fd = os.open(path, os.O_RDONLY)
    try:
        n = min(limit, path.stat().st_size)
        start, done = time.perf_counter(), 0
        while done < n:
            done += len(os.pread(fd, 1 << 16, done))
        return n / (time.perf_counter() - start) / 1e6
    finally:
        os.close(fd)
        drop_page_cache(path)


# (name, discovery frames, fetch in file order)
VARIANTS = (
    ("before", False, False, False),
    ("discovery", True, False, False),
    ("discovery + file order", True, True, False),
    ("+ read-ahead", True, True, True),
)


def cold_complete(
    path: Path,
    poe: float,
    discovery: bool,
    file_order: bool,
    readahead: bool,
    budget: int,
    image: tuple[int, int],
) -> dict:
    saved = outofcore.DISCOVERY_MIN_SIDE
    outofcore.DISCOVERY_MIN_SIDE = saved if discovery else 1 << 30
    try:
        drop_page_cache(path)
        cache = native.BlockCache(budget, 2, "count", file_order=file_order, readahead=readahead)
        with OutOfCoreModel(path, cache) as model:
            camera = frame_bounds(*model.bounds, width=image[0], height=image[1])
            done = model.render_complete(camera, pixels_of_error=poe)
            totals = cache.totals()
            return {
                "seconds": done.seconds,
                "frames": done.frames,
                "read_mib": totals["bytes_read"] / 2**20,
                "working_set_mib": done.stats.working_set_bytes / 2**20,
                "voxel_pct": 100 * done.stats.voxel_hits / max(1, done.stats.primary_rays),
                "image": done.image,
            }
    finally:
        outofcore.DISCOVERY_MIN_SIDE = saved


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", default="1e7,1e8")
    ap.add_argument("--poes", default="2")
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--cache", default="3G")
    ap.add_argument("--image", default="1280x720")
    ap.add_argument("--out", type=Path, default=RESULTS_DIR)
    ap.add_argument("--name", default="complete")
    args = ap.parse_args()
    image = tuple(int(v) for v in args.image.split("x"))
    budget = parse_bytes(args.cache, "--cache")
    rows = []
    for size in (float(s) for s in args.sizes.split(",")):
        path = built_model(int(size))
        rate = cold_read_rate(path)
        print(f"{path.name}: cold read rate {rate:.0f} MB/s", file=sys.stderr, flush=True)
        for poe in (float(p) for p in args.poes.split(",")):
            runs: dict[str, list[dict]] = {name: [] for name, *_ in VARIANTS}
            for _ in range(args.repeats):
                for name, discovery, file_order, readahead in VARIANTS:
                    r = cold_complete(path, poe, discovery, file_order, readahead, budget, image)
                    runs[name].append(r)
                    print(
                        f"  PoE {poe:g} {name}: {r['seconds']:.2f} s, {r['frames']} frames, "
                        f"{r['read_mib']:.0f} MiB read",
                        file=sys.stderr,
                        flush=True,
                    )
            first = runs["before"][0]["image"]
            same = all(np.array_equal(r["image"], first) for rs in runs.values() for r in rs)
            med = {name: statistics.median(r["seconds"] for r in rs) for name, rs in runs.items()}
            new = runs[VARIANTS[-1][0]][0]
            row: dict = {
                "triangles": f"1e{round(math.log10(size))}",
                "poe": poe,
                "cold_read_mb_s": rate,
                "read_mib": new["read_mib"],
                "read_floor_s": new["read_mib"] * 2**20 / 1e6 / rate,
            }
            for name, *_ in VARIANTS:
                row[f"{name} s"] = med[name]
                row[f"{name} frames"] = runs[name][0]["frames"]
            row["speedup"] = med["before"] / med[VARIANTS[-1][0]]
            row["read_rate_mb_s"] = new["read_mib"] * 2**20 / 1e6 / med[VARIANTS[-1][0]]
            row["working_set_mib"] = new["working_set_mib"]
            row["voxel_pct"] = new["voxel_pct"]
            row["images_equal"] = same
            rows.append(row)
    headers = list(rows[0])
    cell = lambda v: f"{v:.3g}" if isinstance(v, float) else v  # noqa: E731
    table = markdown_table(headers, [[cell(r[h]) for h in headers] for r in rows])
    note = (
        f"ISA path {isa_path()}; {args.image} overview, cache {args.cache}, 2 fetchers; page cache dropped "
        f"before every run; medians of {args.repeats} runs of each variant, interleaved. "
        "*read_floor_s*: bytes read / the cold read rate (64 KiB preads in file order).\n\n"
        f"`python bench/complete.py --sizes {args.sizes} --poes {args.poes} --repeats {args.repeats}`"
    )
    args.out.mkdir(parents=True, exist_ok=True)
    title = f"# {args.name}: cold open to complete view"
    (args.out / f"{args.name}.md").write_text(f"{title}\n\n{note}\n\n{table}\n")
    print(table)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
