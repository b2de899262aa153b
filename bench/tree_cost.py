"""A coarser kd-tree against the default one: bytes, frames and what the LOD shows.

Not a test. The builder's SAH costs a node step as `traversal_cost` triangle tests
(default 4). A higher cost builds a coarser tree: fewer nodes and voxels, larger leaves,
a smaller file (docs/FORMAT.md, "Measured choices"). This builds one input at each cost
given, with the same other options, and measures side by side in one run:

* the file: bytes per triangle, node levels' share, LOD levels;
* frames of three views (tradeoff.py's overview, mid and close) at each PoE, every view
  complete, all models open in one cache, the models' frames alternating (medians);
* the working set of each complete view;
* what the LOD shows: each tree's frame at PoE > 0 against the same view at full detail
  (PoE 0) of the default tree (PSNR, SSIM, share of pixels whose hit differs), so both
  trees are judged against one image; and the trees' full-detail frames against each
  other (the same triangles: they differ only where two triangles tie).

    python bench/tree_cost.py bench/.cache/mandelbulb-1e7-s1.ply --costs 4,6 \\
        --options compact_triangles,quantized_vertices --tier-width 0 --name tree-cost-mandelbulb-1e7
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import RESULTS_DIR, command_and_machine, machine_info, markdown_table
from tradeoff import isa_path, psnr, ssim, views

from vastray.build import BuildOptions, build_model
from vastray.modelfile import ModelFile
from vastray.outofcore import OutOfCoreModel, make_cache
from vastray.units import parse_bytes


def build(src: Path, out: Path, cost: float, args: argparse.Namespace) -> dict[str, Any]:
    flags = {name: True for name in args.options.split(",") if name}
    options = BuildOptions(traversal_cost=cost, tier_width=args.tier_width, overwrite=True, **flags)
    start = time.perf_counter()
    report = build_model(src, out, options)
    seconds = time.perf_counter() - start
    with ModelFile(out) as model:
        h = model.header
        tri_first = model.levels[-1][0]
        node_bytes = sum(e.stored_size for e in model.blocks[:tri_first])
        n = h["triangle_count"]
        return {
            "cost": cost,
            "build_s": seconds,
            "b_per_tri": h["file_size"] / n,
            "node_b_per_tri": node_bytes / n,
            "leaves": h["leaves"],
            "refs_per_tri": h["references"] / n,
            "lod_levels": model.node_levels,
            "report": report,
        }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("input", type=Path, help="a mesh (or scene:NAME:TRIANGLES:SEED) to build at each cost")
    ap.add_argument("--costs", default="4,6", help="SAH traversal costs; the first is the reference tree")
    ap.add_argument("--options", default="", help="BuildOptions flags set for every build, comma-separated")
    ap.add_argument("--tier-width", type=float, default=BuildOptions.tier_width)
    ap.add_argument("--poes", default="2,0")
    ap.add_argument("--image", default="1280x720")
    ap.add_argument("--frames", type=int, default=6, help="frames per median, per model and view")
    ap.add_argument("--cache", default="3G")
    ap.add_argument(
        "--scratch", type=Path, default=None, help="where the models go (default: a temporary folder)"
    )
    ap.add_argument("--out", type=Path, default=RESULTS_DIR)
    ap.add_argument("--name", default=None, help="write NAME.md to --out (default: print only)")
    args = ap.parse_args()
    info = machine_info({"command": "python bench/tree_cost.py " + " ".join(sys.argv[1:]), "isa": isa_path()})
    costs = [float(c) for c in args.costs.split(",")]
    poes = [float(p) for p in args.poes.split(",")]
    width, height = (int(v) for v in args.image.split("x"))
    scratch = tempfile.TemporaryDirectory(dir=args.scratch)
    files = {c: Path(scratch.name) / f"cost-{c:g}.vast" for c in costs}
    builds = {}
    for c in costs:
        builds[c] = build(args.input, files[c], c, args)
        print(f"cost {c:g}: built in {builds[c]['build_s']:.1f} s, {builds[c]['b_per_tri']:.2f} B/triangle",
              file=sys.stderr, flush=True)  # fmt: skip

    cache = make_cache(parse_bytes(args.cache), 2)
    models = {c: OutOfCoreModel(files[c], cache) for c in costs}
    cameras = views(models[costs[0]], width, height)
    frames: dict[tuple[float, str, float], list[float]] = {}
    last: dict[tuple[float, str, float], Any] = {}
    working_set: dict[tuple[float, str, float], int] = {}
    for view, camera in cameras.items():
        for poe in poes:
            for c in costs:
                done = models[c].render_complete(camera, pixels_of_error=poe)
                working_set[c, view, poe] = done.stats.working_set_bytes
            for _ in range(args.frames):  # alternating, so load falls on every tree alike
                for c in costs:
                    f = models[c].render(camera, pixels_of_error=poe)
                    frames.setdefault((c, view, poe), []).append(f.stats.milliseconds)
                    last[c, view, poe] = f
            print(f"  {view} PoE {poe:g} done", file=sys.stderr, flush=True)
    for m in models.values():
        m.close()

    ref_cost, full = costs[0], min(poes)
    rows = []
    for view in cameras:
        reference = last[ref_cost, view, full]
        for poe in poes:
            base_ms = statistics.median(frames[ref_cost, view, poe])
            for c in costs:
                f = last[c, view, poe]
                ms = statistics.median(frames[c, view, poe])
                rows.append([
                    view, f"{poe:g}", f"{c:g}", f"{ms:.1f}", f"{ms / base_ms:.2f}",
                    f"{working_set[c, view, poe] / 2**20:.0f}",
                    f"{100 * f.stats.voxel_hits / max(1, f.stats.rays):.1f}",
                    f"{psnr(f.image, reference.image):.1f}", f"{ssim(f.image, reference.image):.4f}",
                    f"{100 * float(np.mean(f.prim != reference.prim)):.2f}",
                ])  # fmt: skip
    table = markdown_table(
        ["view", "PoE", "cost", "frame ms", "vs first", "working set MiB", "voxel %",
         "PSNR dB", "SSIM", "hit differs %"],
        rows,
    )  # fmt: skip
    files_table = markdown_table(
        ["cost", "build s", "B/triangle", "node levels B/triangle", "leaves", "refs/triangle", "LOD levels"],
        [[f"{b['cost']:g}", f"{b['build_s']:.1f}", f"{b['b_per_tri']:.2f}", f"{b['node_b_per_tri']:.2f}",
          f"{b['leaves']:,}", f"{b['refs_per_tri']:.2f}", str(b["lod_levels"])] for b in builds.values()],
    )  # fmt: skip
    print(files_table)
    print(table)
    scratch.cleanup()
    if args.name:
        text = [
            f"# {args.name}: SAH traversal cost {args.costs} on {args.input.name}",
            "",
            __doc__.split("\n\n")[1].replace("\n", " "),
            "",
            f"Every frame is {width}x{height}, 2 threads, the kernels' {isa_path()} path. *vs first*: the "
            f"frame time against the cost-{ref_cost:g} tree's in the same view and PoE. The image columns "
            f"compare each frame with the cost-{ref_cost:g} tree's full-detail (PoE {full:g}) frame of "
            "the view.",
            "",
            *command_and_machine(info),
            "## Files",
            "",
            files_table,
            "",
            "## Frames and images",
            "",
            table,
            "",
        ]
        args.out.mkdir(parents=True, exist_ok=True)
        (args.out / f"{args.name}.md").write_text("\n".join(text))
        print(f"wrote {args.out / (args.name + '.md')}", file=sys.stderr)


if __name__ == "__main__":
    main()
