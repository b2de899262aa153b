"""Reduced precision (paper 004) and compact triangle blocks, each against the plain build.

Not a test. For each model this builds the same input twice, back to back, with
`BuildOptions(quantized_splits=False)` and `=True` (format version 3: 4-byte basic nodes
whose split is a 20-bit step of the node's cell; FORMAT.md §8), then renders both out of
core at full detail (pixels of error 0, every block cached) from the same views and
compares them:

* bytes per triangle, node-level bytes (raw), basic nodes;
* node visits and triangle tests per ray (the renderer's own counters);
* frame time: the median of `--frames` frames per model, the two models alternating
  frame by frame (the ratio is the figure to read on a shared machine);
* image identity: pixels whose hit triangle differs, the largest depth difference, and
  pixels whose colour differs (paper 004: identical images, +1-27 % node tests).

    python bench/precision.py                               # bunny, nefertiti, plant and mandelbulb 1e6
    python bench/precision.py --models plant-1e7,mandelbulb-1e7
    python bench/precision.py --compare vertices --name precision-vertices   # quantized vertices
    python bench/precision.py --compare both --name precision-both           # splits and vertices

`--compare` says what the reduced side is built with: `splits` (the default), `vertices`
(FLAG_QUANTIZED_VERTICES: vertices snapped to a 2^21-step grid of the root cell and
bit-packed per triangle block, FORMAT.md §11; lossy) or `both`; or `compact`, the
compact triangle blocks (FLAG_COMPACT_TRIANGLES, §11a, lossless) against the plain ones.
`--base` names options both sides are built with, e.g. `--compare compact --base
quantized_splits,quantized_vertices`.

    python bench/precision.py --compare compact --name precision-compact

`--baseline-package DIR` also times the full-precision model through an older vastray
package (a folder holding `vastray/` with its native module, e.g. one extracted with
`git archive` beside the module it built): the same frames in child processes, old and
current alternating, on a copy of the model whose version field says 2 (the old reader
refuses version 3; a version-3 model without the flag is laid out as version 2). That
ratio is what carrying cells through the traversal costs full-precision models.

Inputs named NAME-1eK are the binary PLYs bench/build.py caches in bench/.cache (made
there with `vastray scene` when missing); other names are meshes in ../shared/models.
Writes precision.md and precision.csv to bench/results/.
"""

from __future__ import annotations

import argparse
import csv
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

if "--baseline-package" in sys.argv and "--child" in sys.argv:
    # A child timing an older package: it, not the editable install, must be imported.
    sys.meta_path[:] = [f for f in sys.meta_path if "editable" not in type(f).__module__]
    sys.path.insert(0, sys.argv[sys.argv.index("--baseline-package") + 1])

from common import command_and_machine, machine_info, markdown_table, models_dir  # noqa: E402

from vastray.build import BuildOptions, build_model  # noqa: E402
from vastray.camera import frame_bounds  # noqa: E402
from vastray.modelfile import ModelFile, vertex_grid_steps  # noqa: E402
from vastray.outofcore import OutOfCoreModel, make_cache  # noqa: E402

DIRECTIONS = ((0.5, 0.4, 0.8), (-0.7, 0.9, -0.3), (0.1, -0.2, 1.0))


def source_of(name: str, cache: Path) -> Path:
    if "-1e" in name:
        family, size = name.rsplit("-", 1)
        path = cache / f"{name}-s1.ply"
        if not path.exists():
            count = str(int(float(size)))
            cmd = ["vastray", "scene", family, "--triangles", count, "--seed", "1", "-o", str(path)]
            subprocess.run([str(Path(sys.executable).parent / cmd[0]), *cmd[1:]], check=True)
        return path
    return models_dir() / f"{name}.obj"


def child_frames(path: str, width: int, height: int, frames: int) -> None:
    """Child mode: renders `path` out of core at full detail from the DIRECTIONS views,
    `frames` timed frames each after a complete one; prints the frame times as JSON."""
    import json

    from vastray.camera import frame_bounds as bounds_camera
    from vastray.modelfile import ModelFile as File
    from vastray.outofcore import OutOfCoreModel as Model
    from vastray.outofcore import make_cache as cache_of

    with File(path) as m:
        lo, hi = m.bounds
    ms = []
    with Model(path, cache_of(2 << 30, 2)) as model:
        for d in DIRECTIONS:
            cam = bounds_camera(lo, hi, width=width, height=height, direction=d)
            model.render_complete(cam, pixels_of_error=0.0)
            for _ in range(frames):
                ms.append(model.render(cam, pixels_of_error=0.0).stats.milliseconds)
    print(json.dumps(ms))


def baseline_ratio(full: Path, package: Path, args: argparse.Namespace, work: Path) -> dict[str, float]:
    """Median frame time of the full-precision model through `package` and through the
    current code, child processes alternating; and the median of their per-frame ratios."""
    import json
    import os
    import struct
    import zlib

    copy = work / f"{full.stem}-v2.vast"
    data = bytearray(full.read_bytes())
    struct.pack_into("<I", data, 8, 2)
    struct.pack_into("<I", data, 196, 0)
    struct.pack_into("<I", data, 196, zlib.crc32(bytes(data[:256])))
    copy.write_bytes(bytes(data))
    times: dict[str, list[float]] = {"old": [], "new": []}
    for rep in range(args.baseline_reps):
        for kind in ("old", "new") if rep % 2 == 0 else ("new", "old"):
            env = dict(os.environ)
            cmd = [sys.executable, __file__, "--child", str(copy), "--width", str(args.width),
                   "--height", str(args.height), "--frames", str(args.frames)]  # fmt: skip
            if kind == "old":
                cmd += ["--baseline-package", str(package)]
            out = subprocess.run(cmd, env=env, capture_output=True, text=True, check=True).stdout
            times[kind].append(json.loads(out.strip().splitlines()[-1]))
    old = [t for run in times["old"] for t in run]
    new = [t for run in times["new"] for t in run]
    return {
        "base_frame_ms": statistics.median(old),
        "new_frame_ms": statistics.median(new),
        "base_ratio": statistics.median([b / a for a, b in zip(old, new, strict=True)]),
    }


def node_bytes(model: ModelFile) -> int:
    return sum(row["raw_bytes"] for row in model.stats()["levels"][: model.node_levels])


COMPARED = {
    "splits": {"quantized_splits": True},
    "vertices": {"quantized_vertices": True, "quantized_splits": False},
    "both": {"quantized_splits": True, "quantized_vertices": True},
    "compact": {"compact_triangles": True},
}
# What the reference side is built with besides --base: full precision (quantized splits
# are the builder's default), or plain triangle blocks.
REFERENCE = {"compact": {"compact_triangles": False}}
FULL = {"quantized_splits": False}


def labels(compare: str) -> tuple[str, str]:
    """The two sides' names in the tables: (reference, reduced)."""
    return ("plain", "compact") if compare == "compact" else ("full", "quantized")


def side_options(args: argparse.Namespace, reduced: bool) -> dict[str, bool]:
    base = {name: True for name in args.base.split(",") if name}
    own = COMPARED[args.compare] if reduced else REFERENCE.get(args.compare, FULL)
    return {**base, **own}


def measure(name: str, args: argparse.Namespace, work: Path) -> dict[str, Any]:
    src = source_of(name, args.cache)
    row: dict[str, Any] = {"model": name}
    paths = {}
    for quantized in (False, True):
        path = work / f"{name}-{int(quantized)}.vast"
        t0 = time.perf_counter()
        report = build_model(src, path, BuildOptions(overwrite=True, **side_options(args, quantized)))
        key = "q" if quantized else "f"
        row[f"{key}_build_s"] = time.perf_counter() - t0
        with ModelFile(path) as m:
            row[f"{key}_bytes"] = m.header["file_size"]
            row[f"{key}_node_bytes"] = node_bytes(m)
            row[f"{key}_basic"] = m.header["basic_nodes"]
        row["triangles"] = report["triangles"]
        paths[quantized] = path
    cache = make_cache(2 << 30, 2)
    models = {q: OutOfCoreModel(p, cache) for q, p in paths.items()}
    try:
        with ModelFile(paths[False]) as m:
            lo, hi = m.bounds
        cams = [frame_bounds(lo, hi, width=args.width, height=args.height, direction=d) for d in DIRECTIONS]
        differ = depth_err = colour = pixels = coverage = 0
        visits = {False: 0, True: 0}
        tests = {False: 0, True: 0}
        rays = {False: 0, True: 0}
        times: dict[bool, list[float]] = {False: [], True: []}
        for cam in cams:
            frames = {q: models[q].render_complete(cam, pixels_of_error=0.0) for q in (False, True)}
            a, b = frames[False], frames[True]
            pixels += a.prim.size
            differ += int((a.prim != b.prim).sum())
            hit = np.isfinite(a.depth) | np.isfinite(b.depth)
            both = np.isfinite(a.depth) & np.isfinite(b.depth)
            coverage += int((hit & ~both).sum())
            if both.any():
                depth_err = max(depth_err, float(np.abs(a.depth[both] - b.depth[both]).max()))
            colour += int((a.image != b.image).any(axis=2).sum())
            for _ in range(args.frames):
                for q in (False, True) if len(times[False]) % 2 == 0 else (True, False):
                    f = models[q].render(cam, pixels_of_error=0.0)
                    assert f.complete
                    times[q].append(f.stats.milliseconds)
                    visits[q] += f.stats.node_visits
                    tests[q] += f.stats.triangle_tests
                    rays[q] += f.stats.rays
    finally:
        for m in models.values():
            m.close()
    row.update(pixels=pixels, prim_differs=differ, max_depth_error=depth_err, colour_differs=colour,
               coverage_differs=coverage)  # fmt: skip
    with ModelFile(paths[True]) as m:
        row["grid_step"] = max(vertex_grid_steps(m.header["cell_lo"], m.header["cell_hi"]))
    for q, key in ((False, "f"), (True, "q")):
        row[f"{key}_visits_per_ray"] = visits[q] / max(1, rays[q])
        row[f"{key}_tests_per_ray"] = tests[q] / max(1, rays[q])
        row[f"{key}_frame_ms"] = statistics.median(times[q])
    ratios = [tq / tf for tf, tq in zip(times[False], times[True], strict=True)]
    row["frame_ratio"] = statistics.median(ratios)
    if args.baseline_package:
        row.update(baseline_ratio(paths[False], args.baseline_package, args, work))
    return row


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--models", default="stanford-bunny,nefertiti,plant-1e6,mandelbulb-1e6")
    ap.add_argument("--compare", choices=sorted(COMPARED), default="splits", help="what the reduced side has")
    ap.add_argument("--base", default="", help="BuildOptions both sides have, comma separated")
    ap.add_argument("--frames", type=int, default=5, help="timed frames per view and model")
    ap.add_argument("--width", type=int, default=512)
    ap.add_argument("--height", type=int, default=384)
    ap.add_argument("--cache", type=Path, default=HERE / ".cache")
    ap.add_argument("--out", type=Path, default=HERE / "results")
    ap.add_argument("--name", default="precision")
    ap.add_argument("--baseline-package", type=Path, default=None, help="an older vastray package folder")
    ap.add_argument("--baseline-label", default=None, help="its name in the tables (default: the folder)")
    ap.add_argument("--baseline-reps", type=int, default=4, help="child runs per side for the baseline")
    ap.add_argument("--child", default=None, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        child_frames(args.child, args.width, args.height, args.frames)
        return
    args.cache.mkdir(parents=True, exist_ok=True)
    info = machine_info({"command": "python bench/precision.py " + " ".join(sys.argv[1:])})
    rows = []
    with tempfile.TemporaryDirectory(dir=args.cache) as tmp:
        for name in args.models.split(","):
            print(f"{name} ...", file=sys.stderr, flush=True)
            row = measure(name, args, Path(tmp))
            print(f"  {row}", file=sys.stderr, flush=True)
            rows.append(row)
    write(rows, info, args)


def write(rows: list[dict[str, Any]], info: dict[str, str], args: argparse.Namespace) -> None:
    args.out.mkdir(parents=True, exist_ok=True)
    with open(args.out / f"{args.name}.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)

    def pct(a: float, b: float) -> str:
        return f"{a / b - 1:+.1%}"

    size_rows = []
    for r in rows:
        n = r["triangles"]
        size_rows.append([
            r["model"], f"{n:,}", f"{r['f_bytes'] / n:.2f}", f"{r['q_bytes'] / n:.2f}",
            pct(r["q_bytes"], r["f_bytes"]), f"{r['q_basic']:,}", f"{r['f_node_bytes']:,}",
            f"{r['q_node_bytes']:,}", pct(r["q_node_bytes"], r["f_node_bytes"]),
            f"{r['f_build_s']:.2f}", f"{r['q_build_s']:.2f}",
        ])  # fmt: skip
    ref, red = labels(args.compare)
    size = markdown_table(
        ["model", "triangles", f"{ref} B/tri", f"{red} B/tri", "file", "basic nodes", f"node bytes {ref}",
         f"node bytes {red}", "node bytes", f"build s {ref}", f"build s {red}"],
        size_rows,
    )  # fmt: skip
    render_rows = []
    for r in rows:
        render_rows.append([
            r["model"], f"{r['f_visits_per_ray']:.2f}", f"{r['q_visits_per_ray']:.2f}",
            pct(r["q_visits_per_ray"], r["f_visits_per_ray"]), f"{r['f_tests_per_ray']:.2f}",
            f"{r['q_tests_per_ray']:.2f}", pct(r["q_tests_per_ray"], r["f_tests_per_ray"]),
            f"{r['f_frame_ms']:.1f}", f"{r['q_frame_ms']:.1f}", f"**{r['frame_ratio']:.3f}**",
            f"{r['pixels']:,}", f"{r['prim_differs']:,}", f"{r['coverage_differs']:,}",
            f"{r['max_depth_error']:.3g} ({r['max_depth_error'] / r['grid_step']:.2f} steps)",
            f"{r['colour_differs']:,}",
        ])  # fmt: skip
    render = markdown_table(
        ["model", f"node visits/ray {ref}", red, "change", f"triangle tests/ray {ref}", red,
         "change", f"frame ms {ref}", red, "**frame ratio**", "pixels", "hit differs",
         "hit / miss differs", "max depth error (vertex grid steps)", "colour differs"],
        render_rows,
    )  # fmt: skip
    base = ""
    label = args.baseline_label or str(args.baseline_package)
    if any("base_ratio" in r for r in rows):
        base = markdown_table(
            ["model", f"{label} frame ms", "current frame ms", "**current / baseline**"],
            [[r["model"], f"{r['base_frame_ms']:.1f}", f"{r['new_frame_ms']:.1f}",
              f"**{r['base_ratio']:.3f}**"] for r in rows if "base_ratio" in r],
        )  # fmt: skip
        base = (
            "## Full precision: the traversal before and after it carried cells\n\n"
            f"The full-precision model rendered by {label} (its version "
            "field set to 2) and by the current code, the same frames in child processes, alternating, "
            f"{args.baseline_reps} runs each; the ratio is the median over frames of current / baseline.\n\n"
            + base
            + "\n"
        )
    both = ", ".join(f"`{k}`" for k in side_options(args, False) if side_options(args, False)[k]) or "none"
    if args.compare == "compact":
        title = "# Compact triangle blocks against plain ones"
        built = (
            "with plain triangle blocks (docs/FORMAT.md §11) and with compact ones (§11a: leaf records, "
            "groups of 8 triangles with bit-packed corners, ids and palette indices, bit-packed vertices), "
            f"both with these options: {both}"
        )
    else:
        title = f"# Reduced precision: quantized {args.compare} against full precision"
        built = (
            f"at full precision and with {', '.join(f'`{k}`' for k in COMPARED[args.compare])} (quantized "
            "splits: basic nodes of 4 bytes instead of 8, the split a 20-bit step of the node's cell, "
            "docs/FORMAT.md §8; quantized vertices: every vertex snapped to a 2^21-step grid of the root "
            "cell before the tree is built, bit-packed per triangle block, §11); options on both sides: "
            f"{both}"
        )
    lines = [
        title,
        "",
        "Each model is built twice from the same input, back to back (default options, 2 GiB budget), "
        f"{built}. Both are rendered out of core at full detail (pixels of error 0, every block cached), "
        f"{args.width} x {args.height}, "
        f"headlight, {len(DIRECTIONS)} views framing the model; frame times are the median of {args.frames} "
        "frames per view, the two models alternating frame by frame; the *frame ratio* is the median of "
        f"{red} / {ref} over those pairs (below 1: {red} faster). Node visits and triangle tests are "
        "the renderer's counters over the timed frames, per ray (a packet of coherent primary rays counts "
        "one visit per node step it takes together, so visits per ray stay below the tree's depth).",
        "",
        *command_and_machine(info),
        "",
        "## Size",
        "",
        size,
        "",
        "## Rendering and image identity",
        "",
        render,
        "",
        "*hit differs*: pixels whose nearest triangle (input id) differs; *max depth error*: the largest "
        "difference of the hit distance over pixels both hit; *colour differs*: pixels whose 8-bit colour "
        "differs; *hit / miss differs*: pixels that one model hits and the other misses (a silhouette "
        "moved by the vertex snapping). The compact layout is lossless: the same tree, triangles and "
        "vertices, so every pixel should agree. Quantized splits alone are exact (the tree is built on the "
        "planes and the triangles are stored unchanged): the same triangle at the same distance, but for "
        "ties at a shared edge. Quantized vertices move each vertex by at most one grid step per axis, "
        "so a depth differs by at most about sqrt(3) steps along the surface normal, more at a "
        "silhouette or where the ray meets another surface.",
        "",
        base,
    ]
    (args.out / f"{args.name}.md").write_text("\n".join(lines))
    print(f"wrote {args.out / args.name}.md", file=sys.stderr)


if __name__ == "__main__":
    main()
