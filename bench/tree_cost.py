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
  other (the same triangles: they differ only where two triangles tie);
* the same accuracy, not the same PoE: a coarser tree stops fewer rays on voxels at a
  given PoE, so its frame there is slower but nearer full detail. For each of the first
  tree's frames at PoE > 0, the other trees' frame time at the same PSNR, interpolated
  along their PoE curve, and the ratio (a plot, NAME.png, shows the curves).

    python bench/tree_cost.py bench/.cache/mandelbulb-1e7-s1.ply --costs 4,6 \\
        --options compact_triangles,quantized_vertices --tier-width 0 --name tree-cost-mandelbulb-1e7
"""

from __future__ import annotations

import argparse
import itertools
import math
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import (
    RESULTS_DIR,
    alternating_frames,
    command_and_machine,
    fmt,
    machine_info,
    markdown_sections,
    markdown_table,
    pyplot,
    save_figure,
)
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


def time_at_accuracy(curve: list[tuple[float, float]], target: float) -> float:
    """Frame ms at PSNR `target` on a tree's (PSNR, ms) points, linear between the two
    points around it; NaN outside the curve (no PoE reached that accuracy, or every PoE
    passed it)."""
    points = sorted((q, ms) for q, ms in curve if math.isfinite(q))
    for (q0, t0), (q1, t1) in itertools.pairwise(points):
        if q0 <= target <= q1:
            return t0 if q1 == q0 else t0 + (target - q0) / (q1 - q0) * (t1 - t0)
    return math.nan


def plot_curves(
    curves: dict[tuple[float, str], list[tuple[float, float, float]]],
    costs: list[float],
    views: list[str],
    title: str,
    path: Path,
) -> None:
    plt = pyplot()
    if plt is None:
        return
    # A view that every PoE renders at full detail (the close one) has no curve.
    views = [v for v in views if any(math.isfinite(q) for c in costs for _, q, _ in curves[c, v])]
    if not views:
        return
    fig, axes = plt.subplots(1, len(views), figsize=(4.2 * len(views), 3.6))
    for ax, view in zip(np.atleast_1d(axes), views, strict=True):
        for c in costs:
            pts = [(ms, q, poe) for poe, q, ms in curves[c, view] if math.isfinite(q)]
            ax.plot([p[0] for p in pts], [p[1] for p in pts], "o-", label=f"cost {c:g}")
            for ms, q, poe in pts:
                ax.annotate(f"{poe:g}", (ms, q), fontsize=7, xytext=(3, 3), textcoords="offset points")
        ax.set_title(view, fontsize=9)
        ax.set_xlabel("frame ms (median)")
        ax.set_ylabel("PSNR dB against full detail")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    save_figure(fig, title, path)


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
    frames, complete, last, _ = alternating_frames(models, cameras, poes, args.frames)
    working_set = {k: f.stats.working_set_bytes for k, f in complete.items()}
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
    # The same accuracy: each tree's (PoE, PSNR, ms) curve per view, against the first
    # tree's full-detail frame, and the other trees' time at the first tree's PSNR.
    curves: dict[tuple[float, str], list[tuple[float, float, float]]] = {}
    for view in cameras:
        reference = last[ref_cost, view, full]
        for c in costs:
            curves[c, view] = [
                (p, psnr(last[c, view, p].image, reference.image), statistics.median(frames[c, view, p]))
                for p in poes
            ]
    same_rows = []
    for view in cameras:
        for poe, q, ms in curves[ref_cost, view]:
            if not math.isfinite(q):
                continue
            row = [view, f"{poe:g}", f"{q:.1f}", f"{ms:.1f}"]
            for c in costs[1:]:
                t = time_at_accuracy([(cq, cms) for _, cq, cms in curves[c, view]], q)
                row += [fmt(t, 1), fmt(t / ms)]
            same_rows.append(row)
    same_table = markdown_table(
        ["view", "PoE", "PSNR dB", f"cost {ref_cost:g} ms"]
        + [h for c in costs[1:] for h in (f"cost {c:g} ms at that PSNR", "ratio")],
        same_rows,
    )
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
    print(same_table)
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
            *markdown_sections(
                ("Files", "", files_table),
                ("Frames and images", "", table),
                (
                    "The same accuracy",
                    f"Each cost-{ref_cost:g} frame at PoE > 0 (its PSNR against the cost-{ref_cost:g} "
                    "full-detail frame), and the other trees' frame time at that PSNR, linear between "
                    "their two PoEs around it (n/a: none of their PoEs reached or passed it). A ratio "
                    f"under 1: the coarser tree gives the same accuracy faster. The curves: {args.name}.png.",
                    same_table,
                ),
            ),
        ]
        args.out.mkdir(parents=True, exist_ok=True)
        (args.out / f"{args.name}.md").write_text("\n".join(text))
        plot_curves(
            curves,
            costs,
            list(cameras),
            f"{args.name}: frame time against accuracy, by SAH cost",
            args.out / f"{args.name}.png",
        )
        print(f"wrote {args.out / (args.name + '.md')}", file=sys.stderr)


if __name__ == "__main__":
    main()
