"""Voxel errors against the radius: what each LOD test costs at the same accuracy.

Not a test. With voxel errors (format version 8, docs/FORMAT.md §15) a LOD node's test
compares a bound on how far its voxel's box lies from the triangles it stands in for,
floored at a fraction of the box's radius, instead of the radius itself. This builds one
input both ways (and at each floor given), the same tree, and measures side by side in
one run:

* the files: build time, bytes per triangle, LOD nodes whose error is under their radius;
* each view (tradeoff.py's overview and mid) at each PoE, complete, all models open in
  one cache, their frames alternating (medians): frame time, working set, voxel and
  triangle pixels, PSNR and SSIM against the full-detail (PoE 0) frame, the same for all;
* the same accuracy, not the same PoE: errors stop more rays on voxels at a given PoE,
  so their frame there is faster but further from full detail. For each radius frame at
  PoE > 0, each other variant's frame time and working set at the same PSNR,
  interpolated along its PoE curve, and their ratios (NAME.png plots the curves).

    python bench/lod_error.py bench/.cache/plant-1e8-s1.ply --floors 0.5,0.25 --views overview \\
        --cache 10G --name lod-error-plant-1e8   # 3 models of 4 GB, each needing 2 GiB at PoE 0
"""

from __future__ import annotations

import argparse
import json
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
from tree_cost import time_at_accuracy as at_accuracy  # any value along a (PSNR, value) curve

from vastray.build import BuildOptions, build_model
from vastray.outofcore import OutOfCoreModel, make_cache
from vastray.units import parse_bytes

RADIUS = "radius"


def label(variant: str) -> str:
    return "radius" if variant == RADIUS else f"errors, floor {variant}"


def build(src: Path, out: Path, variant: str, memory: int) -> dict[str, Any]:
    """Builds `out` (or, with --keep, reuses it and the report saved beside it)."""
    saved = out.with_suffix(".json")
    if out.exists() and saved.exists():
        return json.loads(saved.read_text())
    errors = {"voxel_errors": False} if variant == RADIUS else {"voxel_error_floor": float(variant)}
    start = time.perf_counter()
    report = build_model(src, out, BuildOptions(memory=memory, overwrite=True, **errors))
    result = {"seconds": time.perf_counter() - start, "report": report}
    saved.write_text(json.dumps(result, default=str))
    return result


def plot(curves: dict[tuple[str, str], list[tuple[float, float, float, float]]], variants: list[str],
         cameras: list[str], title: str, path: Path) -> None:  # fmt: skip
    plt = pyplot()
    if plt is None:
        return
    fig, axes = plt.subplots(2, len(cameras), figsize=(4.4 * len(cameras), 7.0), squeeze=False)
    for col, view in enumerate(cameras):
        for variant in variants:
            pts = [p for p in curves[variant, view] if math.isfinite(p[1])]
            for row, x in ((0, 2), (1, 3)):
                ax = axes[row][col]
                ax.plot([p[x] for p in pts], [p[1] for p in pts], "o-", label=label(variant))
                for p in pts:
                    ax.annotate(
                        f"{p[0]:g}", (p[x], p[1]), fontsize=7, xytext=(3, 3), textcoords="offset points"
                    )
                ax.set_xlabel("frame ms (median)" if row == 0 else "working set MiB")
                ax.set_ylabel("PSNR dB against full detail")
                ax.set_title(view, fontsize=9)
                ax.grid(alpha=0.3)
                ax.legend(fontsize=8)
    save_figure(fig, title, path)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("input", type=Path, help="a mesh (or scene:NAME:TRIANGLES:SEED)")
    ap.add_argument(
        "--floors", default="0.25", help="voxel_error_floor of each errors build, comma-separated"
    )
    ap.add_argument("--poes", default="2,3,4,6,0", help="PoEs; the smallest is the full-detail reference")
    ap.add_argument("--views", default="overview,mid")
    ap.add_argument("--image", default="1280x720")
    ap.add_argument("--frames", type=int, default=5, help="frames per median, per model, view and PoE")
    ap.add_argument("--cache", default="6G")
    ap.add_argument("--memory", default="2G", help="the builds' memory budget")
    ap.add_argument(
        "--scratch", type=Path, default=None, help="where the models go (default: a temporary folder)"
    )
    ap.add_argument(
        "--keep", type=Path, default=None, help="build the models here and keep them; reuse them if there"
    )
    ap.add_argument("--out", type=Path, default=RESULTS_DIR)
    ap.add_argument("--name", default=None, help="write NAME.md and NAME.png to --out (default: print only)")
    args = ap.parse_args()
    info = machine_info({"command": "python bench/lod_error.py " + " ".join(sys.argv[1:]), "isa": isa_path()})
    variants = [RADIUS, *args.floors.split(",")]
    poes = [float(p) for p in args.poes.split(",")]
    full = min(poes)
    width, height = (int(v) for v in args.image.split("x"))
    scratch = tempfile.TemporaryDirectory(dir=args.scratch)
    folder = Path(scratch.name)
    if args.keep is not None:
        args.keep.mkdir(parents=True, exist_ok=True)
        folder = args.keep
    files = {v: folder / f"{args.input.stem}-{v}.vast" for v in variants}
    builds = {}
    for v in variants:
        builds[v] = build(args.input, files[v], v, parse_bytes(args.memory))
        print(f"{label(v)}: built in {builds[v]['seconds']:.1f} s", file=sys.stderr, flush=True)

    cache = make_cache(parse_bytes(args.cache), 2)
    models = {v: OutOfCoreModel(files[v], cache) for v in variants}
    cameras = {k: c for k, c in views(models[RADIUS], width, height).items() if k in args.views.split(",")}
    # `last`: each variant's complete frame, for its image and counts.
    ms, last, _, incomplete = alternating_frames(models, cameras, poes, args.frames)
    for m in models.values():
        m.close()

    files_rows = []
    for v, b in builds.items():
        r = b["report"]
        below = r.get("lod_errors_below_radius", 0) if v != RADIUS else 0
        files_rows.append([label(v), f"{b['seconds']:.1f}", f"{r['bytes_per_triangle']:.2f}",
                           f"{r['lod_nodes']:,}",
                           f"{100 * below / max(1, r['lod_nodes']):.1f}",
                           f"{r.get('voxel_error_ms', 0) / 1000:.1f}" if v != RADIUS else "-"])  # fmt: skip
    rows = []
    curves: dict[tuple[str, str], list[tuple[float, float, float, float]]] = {}
    for view in cameras:
        reference = last[RADIUS, view, full]
        for poe in poes:
            for v in variants:
                f = last[v, view, poe]
                t, mib = statistics.median(ms[v, view, poe]), f.stats.working_set_bytes / 2**20
                q = psnr(f.image, reference.image)
                if poe > full:
                    curves.setdefault((v, view), []).append((poe, q, t, mib))
                rows.append([view, f"{poe:g}", label(v), f"{t:.1f}", f"{mib:.0f}",
                             f"{100 * f.stats.voxel_hits / max(1, f.stats.rays):.1f}",
                             f"{100 * float(np.mean(f.prim >= 0)):.1f}", f"{q:.2f}",
                             f"{ssim(f.image, reference.image):.4f}"])  # fmt: skip
    same_rows = []
    for view in cameras:
        for poe, q, t, mib in curves[RADIUS, view]:
            if not math.isfinite(q):
                continue
            row = [view, f"{poe:g}", f"{q:.2f}", f"{t:.1f}", f"{mib:.0f}"]
            for v in variants[1:]:
                at_t = at_accuracy([(c[1], c[2]) for c in curves[v, view]], q)
                at_mib = at_accuracy([(c[1], c[3]) for c in curves[v, view]], q)
                row += [fmt(at_t, 1), fmt(at_t / t), fmt(at_mib, 0), fmt(at_mib / mib)]
            same_rows.append(row)
    files_table = markdown_table(
        ["LOD test", "build s", "B/triangle", "LOD nodes", "under their radius %", "errors s"], files_rows
    )
    table = markdown_table(
        [
            "view",
            "PoE",
            "LOD test",
            "frame ms",
            "working set MiB",
            "voxel px %",
            "triangle px %",
            "PSNR dB",
            "SSIM",
        ],
        rows,
    )
    same_table = markdown_table(
        ["view", "PoE", "PSNR dB", "radius ms", "radius MiB"]
        + [h for v in variants[1:] for h in (f"{label(v)}: ms", "ratio", "MiB", "ratio")],
        same_rows,
    )
    if incomplete:
        print(f"warning: {incomplete} timed frames were incomplete: raise --cache", file=sys.stderr)
    print(files_table)
    print(table)
    print(same_table)
    scratch.cleanup()
    if args.name:
        text = [
            f"# {args.name}: voxel errors against the radius on {args.input.name}",
            "",
            __doc__.split("\n\n")[1].replace("\n", " "),
            "",
            f"Every frame is {width}x{height}, complete ({incomplete} timed frames were not), 2 threads, "
            f"the kernels' {isa_path()} path. The "
            f"image columns compare each frame with the radius build's full-detail (PoE {full:g}) frame of "
            "the view (the trees are the same, so every build's full-detail frame is that one).",
            "",
            *command_and_machine(info),
            *markdown_sections(
                ("Files", "", files_table),
                ("Frames and images", "", table),
                (
                    "The same accuracy",
                    "Each radius frame at PoE > 0 (its PSNR against full detail), and each errors "
                    "build's frame time and working set at that PSNR, linear between its two PoEs around "
                    "it (n/a: none of its PoEs reached or passed it). Ratios under 1: the same accuracy "
                    f"for less. The curves: {args.name}.png.",
                    same_table,
                ),
            ),
        ]
        args.out.mkdir(parents=True, exist_ok=True)
        (args.out / f"{args.name}.md").write_text("\n".join(text))
        plot(curves, variants, list(cameras), f"{args.name}: accuracy against frame time and working set",
             args.out / f"{args.name}.png")  # fmt: skip
        print(f"wrote {args.out / (args.name + '.md')}", file=sys.stderr)


if __name__ == "__main__":
    main()
