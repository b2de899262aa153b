"""Scaling past 2 cores: the renderer and the builder at 1, 2, 4 ... N threads, on one
machine, in one run.

    python bench/scaling.py [--models plant,mandelbulb] [--size 1e7] [--threads 1,2,4,8,16]

Each model is generated once and built with every thread count (the plant from a PLY
file, as a user's build reads one; the other models from their scene source, built
once with all threads). Then, one 1280x720 view of the whole model, at each thread
count, the median of `--repeats` frames of:

* `in-core` and `in-core ao`: the in-core renderer on the model's own tree (headlight;
  ambient occlusion, its default samples);
* `lod`, `lod sun`, `lod indirect`: the out-of-core renderer at 2 pixels of error,
  headlight, with shadow rays, and with one bounce of indirect light; `full`: at full
  detail. Each view is complete (every block it needs in the cache) before it is timed,
  so these are frame times, not loading times.

Speedup is the 1-thread time over the N-thread time; efficiency is speedup / N. The
server's side of scaling (many viewers on one machine) is bench/stream.py. Results go
to bench/results/NAME.md (+ .csv, .png); the ISA path that ran is in the table's head.
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import statistics
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import RESULTS_DIR, format_count, machine_info, markdown_table, parse_count, pyplot, save_figure

from vastray import native
from vastray.build import BuildOptions, build_model
from vastray.camera import Camera, frame_bounds
from vastray.modelfile import ModelFile
from vastray.outofcore import OutOfCoreModel, make_cache
from vastray.renderer import trace
from vastray.scenes import write_scene
from vastray.units import parse_bytes

WIDTH, HEIGHT = 1280, 720
POE = 2.0


def default_threads() -> list[int]:
    """Powers of two up to the hardware threads, and the hardware threads themselves."""
    n = native.hardware_threads()
    counts = [1 << k for k in range(n.bit_length()) if 1 << k <= n]
    return counts if counts[-1] == n else [*counts, n]


def timed_build(source: str, out: Path, threads: int) -> float:
    start = time.perf_counter()
    build_model(source, out, BuildOptions(threads=threads, overwrite=True))
    return time.perf_counter() - start


def study_builds(
    name: str, size: int, threads: list[int], workdir: Path
) -> tuple[Path, list[dict[str, Any]]]:
    """Builds `name` with each thread count (from a PLY file); the model and the rows."""
    ply = workdir / f"{name}.ply"
    start = time.perf_counter()
    write_scene(name, size, 1, ply)
    print(f"  {name}: PLY written in {time.perf_counter() - start:.1f} s", file=sys.stderr, flush=True)
    out = workdir / f"{name}.vast"
    rows = []
    for t in threads:
        seconds = timed_build(str(ply), out, t)
        rows.append({"model": name, "workload": "build", "threads": t, "ms": 1000 * seconds,
                     "mrays_per_s": math.nan})  # fmt: skip
        print(f"  {name} build, {t} threads: {seconds:.1f} s", file=sys.stderr, flush=True)
    ply.unlink()
    return out, rows


def median_frame_ms(render: Callable[[], Any], repeats: int) -> tuple[float, float]:
    """Median frame time (the renderer's own clock) and rays per second of that frame."""
    frames = [render() for _ in range(repeats)]
    ms = statistics.median(f.stats.milliseconds for f in frames)
    rays = statistics.median(f.stats.rays for f in frames)
    return ms, rays / ms / 1e3


def study_frames(
    name: str, path: Path, threads: list[int], repeats: int, cache_bytes: int
) -> list[dict[str, Any]]:
    cache = make_cache(cache_bytes, fetchers=2)
    model = OutOfCoreModel(path, cache)
    camera: Camera = frame_bounds(*model.bounds, width=WIDTH, height=HEIGHT)
    # Complete each view once, with every thread, so that the timed frames find their blocks.
    for poe, shading in ((POE, "headlight"), (POE, "sun"), (POE, "indirect"), (0.0, "headlight")):
        model.render_complete(camera, pixels_of_error=poe, shading=shading)
    with ModelFile(path) as f:
        scene = f.to_scene()
    cam = camera.to_native()
    workloads: dict[str, Callable[[int], Any]] = {
        "in-core": lambda t: trace(scene, cam, shading="headlight", threads=t),
        "in-core ao": lambda t: trace(scene, cam, shading="ao", threads=t),
        "lod": lambda t: model.render(camera, pixels_of_error=POE, threads=t),
        "lod sun": lambda t: model.render(camera, pixels_of_error=POE, shading="sun", threads=t),
        "lod indirect": lambda t: model.render(camera, pixels_of_error=POE, shading="indirect", threads=t),
        "full": lambda t: model.render(camera, pixels_of_error=0.0, threads=t),
    }
    rows = []
    for workload, render in workloads.items():
        for t in threads:
            ms, mrays = median_frame_ms(lambda: render(t), repeats)  # noqa: B023
            rows.append({"model": name, "workload": workload, "threads": t, "ms": ms, "mrays_per_s": mrays})
            print(
                f"  {name} {workload}, {t} threads: {ms:.1f} ms, {mrays:.1f} Mrays/s",
                file=sys.stderr,
                flush=True,
            )
    model.close()
    return rows


def with_speedups(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    for r in rows:
        one = next(x for x in rows if x["model"] == r["model"] and x["workload"] == r["workload"]
                   and x["threads"] == 1)  # fmt: skip
        r["speedup"] = one["ms"] / r["ms"]
        r["efficiency"] = r["speedup"] / r["threads"]
    return rows


def write(rows: list[dict[str, Any]], info: dict[str, str], out: Path) -> None:
    out.parent.mkdir(parents=True, exist_ok=True)
    with open(out.with_suffix(".csv"), "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    threads = sorted({r["threads"] for r in rows})
    table = []
    for key in dict.fromkeys((r["model"], r["workload"]) for r in rows):
        cells = {r["threads"]: r for r in rows if (r["model"], r["workload"]) == key}
        unit = "s" if key[1] == "build" else "ms"
        scale = 1e-3 if unit == "s" else 1.0
        table.append([
            *key,
            *(f"{cells[t]['ms'] * scale:.1f} {unit} ({cells[t]['speedup']:.1f}x)" for t in threads),
            f"{cells[threads[-1]]['efficiency']:.0%}",
            f"{cells[threads[-1]]['mrays_per_s']:.1f}" if key[1] != "build" else "",
        ])  # fmt: skip
    headers = ["model", "workload", *(f"{t} T" for t in threads), f"efficiency at {threads[-1]}",
               f"Mrays/s at {threads[-1]}"]  # fmt: skip
    head = "\n".join(f"- {k}: {v}" for k, v in info.items())
    text = (
        "# Scaling past 2 cores: renderer and builder against the thread count\n\n"
        "`python bench/scaling.py` — time per frame (median, the renderer's clock; 1280x720, "
        "whole model in view, complete views) or per build (wall clock), and in brackets "
        "the speedup over 1 thread.\n\n"
        f"{head}\n\n{markdown_table(headers, table)}\n"
    )
    out.with_suffix(".md").write_text(text)
    print(text)
    plot(rows, threads, out.with_suffix(".png"), info)


def plot(rows: list[dict[str, Any]], threads: list[int], path: Path, info: dict[str, str]) -> None:
    plt = pyplot()
    if plt is None:
        return

    models = list(dict.fromkeys(r["model"] for r in rows))
    fig, axes = plt.subplots(1, len(models), figsize=(5.5 * len(models), 4.2), squeeze=False)
    for ax, name in zip(axes[0], models, strict=True):
        for workload in dict.fromkeys(r["workload"] for r in rows if r["model"] == name):
            pts = [r for r in rows if r["model"] == name and r["workload"] == workload]
            ax.plot([r["threads"] for r in pts], [r["speedup"] for r in pts], marker="o", label=workload)
        ax.plot(threads, threads, color="grey", linestyle=":", label="ideal")
        ax.set(xscale="log", yscale="log", xlabel="threads", ylabel="speedup over 1 thread", title=name)
        ax.set_xticks(threads, [str(t) for t in threads])
        ax.legend(fontsize=8)
    save_figure(fig, f"vastray scaling, {info.get('cpu', '')}, ISA {info.get('isa path', '')}", path)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--models", default="plant,mandelbulb")
    ap.add_argument("--size", default="1e7", help="triangles per model")
    ap.add_argument("--threads", default="", help="comma-separated thread counts (default: 1, 2, 4 ... all)")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--build-models", default="plant", help="models whose build is timed at each count")
    ap.add_argument("--cache", default="4G", help="block cache for the out-of-core frames")
    ap.add_argument("--name", default="scaling")
    ap.add_argument("--out", default=str(RESULTS_DIR))
    args = ap.parse_args()
    size = parse_count(args.size)
    threads = [int(t) for t in args.threads.split(",")] if args.threads else default_threads()
    if threads[0] != 1:
        threads = [1, *threads]
    info = machine_info({
        "isa path": native.isa(),
        "vastray hardware threads": str(native.hardware_threads()),
        "triangles per model": format_count(size),
        "block cache": args.cache,
    })  # fmt: skip
    rows: list[dict[str, Any]] = []
    Path(args.out).mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix="vastray-scaling-") as tmp:
        for name in args.models.split(","):
            if name in args.build_models.split(","):
                path, built = study_builds(name, size, threads, Path(tmp))
                rows += built
            else:
                path = Path(tmp) / f"{name}.vast"
                seconds = timed_build(f"scene:{name}:{size}:1", path, 0)
                print(
                    f"  {name}: built from its scene source in {seconds:.1f} s", file=sys.stderr, flush=True
                )
            rows += study_frames(name, path, threads, args.repeats, parse_bytes(args.cache))
            path.unlink()
            (Path(args.out) / f"{args.name}.partial.json").write_text(json.dumps(rows))
    write(with_speedups(rows), info, Path(args.out) / args.name)
    (Path(args.out) / f"{args.name}.partial.json").unlink(missing_ok=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
