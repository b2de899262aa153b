"""Untiered against tiered layouts of the same model, side by side (issue 12, FORMAT.md §15).

For each model file given (label=path: builds of one input, one untiered, one tiered),
the 1280x720 overview (vastray.camera.frame_bounds) at each pixels of error:

* cold open -> complete: the page cache dropped, a fresh cache, render_complete; its
  seconds and frames, the bytes the fetchers read, the working set and the share of
  primary rays that end on voxels;
* frame time of the complete view, single rays and 4x4 packets: all models open in one
  cache, complete, then frames of the models in turn, --frames each (medians), so load
  from elsewhere on the machine falls on all alike;
* the file: size, bytes per triangle, blocks, tiers.

Models are measured in turn within each repeat, so all see the same machine; the
images of the models must be equal (layout changes what is read, never what is drawn).
`--build INPUT` first builds INPUT with this vastray at each of `--widths` (default:
untiered and the default tier width; --tier-width 0 writes the untiered layout, byte for
byte that of format version 4 apart from the header's version) and reports their build
times.

    python bench/tiers.py --models untiered=bench/.cache/plant-1e7-v4.vast,tiered=bench/.cache/plant-1e7.vast
    python bench/tiers.py --build bench/.cache/plant-1e7-s1.ply --name tiers-1e7
    python bench/tiers.py --build bench/.cache/plant-1e7-s1.ply --widths 0,1,2,3 --name tier-widths-1e7
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import RESULTS_DIR, machine_info, markdown_table
from tradeoff import frame_ms, isa_path

from vastray import native
from vastray.build import BuildOptions, build_model
from vastray.camera import frame_bounds
from vastray.modelfile import ModelFile
from vastray.outofcore import OutOfCoreModel
from vastray.pagecache import drop_page_cache
from vastray.units import parse_bytes


def file_row(path: Path) -> dict[str, Any]:
    with ModelFile(path) as m:
        n = m.header["triangle_count"]
        return {
            "file_mib": m.header["file_size"] / 2**20,
            "b_per_tri": m.header["file_size"] / n,
            "blocks": len(m.blocks),
            "tiers": m.tier_count if m.tiered else 0,
        }


def cold_complete(path: Path, poe: float, budget: int, image: tuple[int, int]) -> dict[str, Any]:
    drop_page_cache(path)
    start = time.perf_counter()
    cache = native.BlockCache(budget, 2, "count")
    with OutOfCoreModel(path, cache) as model:
        camera = frame_bounds(*model.bounds, width=image[0], height=image[1])
        done = model.render_complete(camera, pixels_of_error=poe)
        return {
            "cold_complete_s": time.perf_counter() - start,  # open included
            "frames": done.frames,
            "read_mib": cache.totals()["bytes_read"] / 2**20,
            "working_set_mib": done.stats.working_set_bytes / 2**20,
            "working_set_blocks": done.stats.working_set_blocks,
            "voxel_pct": 100 * done.stats.voxel_hits / max(1, done.stats.primary_rays),
            "image": done.image,
        }


def frame_times(paths: dict[str, Path], poe: float, budget: int, image: tuple[int, int], frames: int) -> dict:
    """{label: {packets: median ms}} of the complete views, frames of the models in turn."""
    cache = native.BlockCache(budget, 2, "count")
    models = {label: OutOfCoreModel(path, cache) for label, path in paths.items()}
    try:
        cameras = {k: frame_bounds(*m.bounds, width=image[0], height=image[1]) for k, m in models.items()}
        for k, m in models.items():
            m.render_complete(cameras[k], pixels_of_error=poe)
        out: dict[str, dict[int, float]] = {k: {} for k in models}
        for packets in (1, 16):
            times: dict[str, list[float]] = {k: [] for k in models}
            for _ in range(frames):
                for k, m in models.items():
                    ms, _ = frame_ms(m, cameras[k], 1, pixels_of_error=poe, packets=packets)
                    times[k].append(ms)
            for k, t in times.items():
                out[k][packets] = statistics.median(t)
        return out
    finally:
        for m in models.values():
            m.close()


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--models", default="", help="label=path,label=path: the files to compare")
    ap.add_argument("--build", type=Path, help="build this input untiered and tiered first")
    ap.add_argument(
        "--widths",
        default=f"0,{BuildOptions.tier_width:g}",
        help="with --build: the tier widths to build (octaves; 0: untiered), e.g. 0,1,2,3",
    )
    ap.add_argument("--poes", default="2")
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--frames", type=int, default=8, help="frames per frame-time median")
    ap.add_argument("--cache", default="3G")
    ap.add_argument("--image", default="1280x720")
    ap.add_argument("--out", type=Path, default=RESULTS_DIR)
    ap.add_argument("--name", default=None, help="write NAME.md to --out (default: print only)")
    args = ap.parse_args()
    image = tuple(int(v) for v in args.image.split("x"))
    budget = parse_bytes(args.cache, "--cache")
    models: dict[str, Path] = {}
    builds: dict[str, float] = {}
    for item in filter(None, args.models.split(",")):
        label, _, path = item.partition("=")
        models[label] = Path(path)
    if args.build is not None:
        stem = args.build.stem.removesuffix("-s1")
        for width in (float(w) for w in args.widths.split(",")):
            label = "untiered" if width == 0 else f"tiered-w{width:g}"
            out = args.build.parent / f"{stem}-{label}.vast"
            drop_page_cache(args.build)
            report = build_model(args.build, out, BuildOptions(tier_width=width, overwrite=True))
            builds[label] = report["seconds"]
            models[label] = out
            print(f"{label}: built in {report['seconds']:.1f} s", file=sys.stderr, flush=True)
    rows = []
    for poe in (float(p) for p in args.poes.split(",")):
        runs: dict[str, list[dict[str, Any]]] = {label: [] for label in models}
        for _ in range(args.repeats):
            for label, path in models.items():
                r = cold_complete(path, poe, budget, image)
                runs[label].append(r)
                print(
                    f"  PoE {poe:g} {label}: {r['cold_complete_s']:.2f} s, {r['read_mib']:.0f} MiB read, "
                    f"working set {r['working_set_mib']:.0f} MiB",
                    file=sys.stderr,
                    flush=True,
                )
        images = [r["image"] for rs in runs.values() for r in rs]
        same = all(np.array_equal(images[0], im) for im in images)
        # Both working sets at once: the budget must hold their sum.
        ms = frame_times(models, poe, budget * max(1, len(models)), image, args.frames)
        for label, rs in runs.items():
            row: dict[str, Any] = {"model": label, "poe": poe, **file_row(models[label])}
            row["cold_complete_s"] = statistics.median(r["cold_complete_s"] for r in rs)
            row["frame_ms_p1"], row["frame_ms_p16"] = ms[label][1], ms[label][16]
            for key in ("frames", "read_mib", "working_set_mib", "working_set_blocks", "voxel_pct"):
                row[key] = rs[0][key]
            if label in builds:
                row["build_s"] = builds[label]
            row["images_equal"] = same
            rows.append(row)
    headers = list(dict.fromkeys(k for r in rows for k in r))

    def cell(v: Any) -> Any:
        if not isinstance(v, float):
            return f"{v:,}" if isinstance(v, int) and not isinstance(v, bool) else v
        return f"{v:,.0f}" if abs(v) >= 100 else f"{v:.3g}"

    table = markdown_table(headers, [[cell(r.get(h, "")) for h in headers] for r in rows])
    print(table)
    if args.name:
        info = machine_info({"command": "python bench/tiers.py " + " ".join(sys.argv[1:])})
        note = (
            f"ISA path {isa_path()}; {args.image} overview, cache {args.cache}, 2 fetchers; page cache "
            f"dropped before every open; medians of {args.repeats} runs, models interleaved; frame times: "
            f"medians of {args.frames} frames of each complete view, all open in one cache, frames in "
            "turn. *cold_complete_s* counts the open."
        )
        title = f"# {args.name}: untiered and tiered layouts"
        text = [title, "", note, "", "```sh", info["command"], "```", ""]
        text += [f"- {k}: {v}" for k, v in info.items() if k != "command"]
        args.out.mkdir(parents=True, exist_ok=True)
        (args.out / f"{args.name}.md").write_text("\n".join([*text, "", table, ""]))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
