"""Speed against accuracy of out-of-core LOD rendering (paper 000 §6, Fig. 7).

Six studies, each printed as a table and written to bench/results/tradeoff-*.{md,csv}
with plots (tradeoff-*.png); every table names the kernels' ISA path (native.isa()):

  poe      For fixed views of one model: pixels of error (PoE) in {0, .5, 1, 2, 3, 8, 32}
           x shading (headlight, sun, ao, indirect) -> frame time, rays/s, working set, and the
           image error against the PoE 0 complete image: PSNR, SSIM and the share of
           pixels whose hit differs. Every frame is rendered once its view is complete at
           that PoE, so the numbers measure the LOD, not data still loading.
  size     Frame time against model size (10^5 ... 10^8 triangles) with LOD (PoE 2) and
           without (PoE 0, full detail), single rays against 2x2 and 4x4 packets, sun and
           indirect beside headlight, the instant-on time (open + first frame, page cache
           dropped), and up to 10^7 the in-core renderer on the same model decoded whole
           (ModelFile.to_scene), side by side: the out-of-core / in-core ratio (against the
           renderer's wide-BVH primary rays, and against its kd-tree packets, the same walk).
  pixels   Working set and time to complete of one view against its pixel count (320x180
           ... 1920x1080) at PoE 2: with level of detail the pixels, not the triangles,
           should set the working set.
  loading  Time until a view is complete against cache budget, fetcher count and fetch
           priority (paper 000 request counts against paper 003 projected size).
  ooc      Out of core for real: a model file several times the cache budget along a
           scripted camera path; resident memory per frame against the budget, frame
           times, and whether frames keep coming while data loads.
  projection  Orthographic against perspective views of the same framing (iso, front,
           top) at PoE 2: frame time with single rays and 4x4 packets, per pixel that hits
           the model (the orthographic framing is tighter), and the working set.

Disk reads are real: before every run that measures loading, the model file's pages are
dropped from the OS page cache with posix_fadvise(POSIX_FADV_DONTNEED) (bench/build.py's
drop_page_cache), so the fetchers read from the device, not from memory.

Models are the `plant` scene at 10^K triangles, generated once into bench/.cache as PLY
and built there as plant-1eK.vast (the 10^8 build takes about five minutes).

    python bench/tradeoff.py                      # all studies
    python bench/tradeoff.py --studies poe,size --sizes 1e5,1e6,1e7
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path
from typing import Any
from unittest import mock

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import RESULTS_DIR, machine_info, markdown_table, pyplot, save_figure

from vastray import native
from vastray.camera import PROJECTIONS, Camera, frame_bounds
from vastray.modelfile import ModelFile
from vastray.outofcore import CacheTooSmallError, OutOfCoreModel, make_cache
from vastray.pagecache import drop_page_cache  # fsync, then POSIX_FADV_DONTNEED
from vastray.renderer import RENDER_PARAM_FIELDS, trace
from vastray.units import parse_bytes

CACHE = Path(__file__).resolve().parent / ".cache"
POES = (0.0, 0.5, 1.0, 2.0, 3.0, 8.0, 32.0)
# The modes this build has (the script also measures builds from before issue 12).
SHADINGS = tuple(m for m in ("headlight", "sun", "ao", "indirect") if m in native.SHADING_MODES)


def isa_path() -> str:
    return native.isa() if hasattr(native, "isa") else "sse2 (no dispatch)"


def optional(**fields: Any) -> dict[str, Any]:
    """The render parameters of `fields` that this build knows."""
    return {k: v for k, v in fields.items() if k in RENDER_PARAM_FIELDS}


# ----------------------------------------------------------------------------- models


def built_model(size: int) -> Path:
    """bench/.cache/plant-1eK.vast, generated and built when missing."""
    label = f"1e{round(math.log10(size))}"
    out = CACHE / f"plant-{label}.vast"
    if out.exists():
        return out
    CACHE.mkdir(parents=True, exist_ok=True)
    ply = CACHE / f"plant-{label}-s1.ply"
    vastray = [sys.executable, "-m", "vastray"]
    if not ply.exists():
        print(f"  generating {ply}", file=sys.stderr, flush=True)
        subprocess.run(
            [*vastray, "scene", "plant", "--triangles", str(size), "--seed", "1", "-o", str(ply)], check=True
        )
    print(f"  building {out}", file=sys.stderr, flush=True)
    subprocess.run([*vastray, "build", str(ply), "-o", str(out), "--force"], check=True)
    return out


def views(model: OutOfCoreModel, width: int, height: int) -> dict[str, Camera]:
    """An overview, a mid-range and a close-up view of the model, from the same side."""
    lo, hi = (np.asarray(v) for v in model.bounds)
    overview = frame_bounds(lo, hi, width=width, height=height)
    eye, target = np.asarray(overview.eye), np.asarray(overview.target)
    out = {"overview": overview}
    for name, f in (("mid", 0.5), ("close", 0.2)):
        out[name] = Camera(
            eye=tuple(target + (eye - target) * f), target=overview.target, width=width, height=height
        )
    return out


# ----------------------------------------------------------------------------- image error


def luminance(image: np.ndarray) -> np.ndarray:
    return image.astype(np.float64) @ np.array([0.299, 0.587, 0.114])


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = float(np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2))
    return math.inf if mse == 0 else 10 * math.log10(255.0**2 / mse)


def ssim(a: np.ndarray, b: np.ndarray) -> float:
    """Mean SSIM of the luminance (Wang et al. 2004: 11x11 Gaussian window, sigma 1.5)."""
    from scipy.ndimage import gaussian_filter

    x, y = luminance(a), luminance(b)
    c1, c2 = (0.01 * 255) ** 2, (0.03 * 255) ** 2
    blur = lambda z: gaussian_filter(z, 1.5, truncate=3.5)  # noqa: E731
    mx, my = blur(x), blur(y)
    vx, vy, cxy = blur(x * x) - mx * mx, blur(y * y) - my * my, blur(x * y) - mx * my
    s = ((2 * mx * my + c1) * (2 * cxy + c2)) / ((mx * mx + my * my + c1) * (vx + vy + c2))
    return float(s.mean())


# ----------------------------------------------------------------------------- measuring


def frame_ms(model: OutOfCoreModel, camera: Camera, repeats: int, **kw: Any) -> tuple[float, Any]:
    """Median frame time of `repeats` frames of an already complete view."""
    frames = [model.render(camera, **kw) for _ in range(repeats)]
    return statistics.median(f.stats.milliseconds for f in frames), frames[-1]


def study_poe(args: argparse.Namespace) -> list[dict[str, Any]]:
    path = built_model(args.study_size)
    cache = make_cache(args.cache, 2)
    rows = []
    with OutOfCoreModel(path, cache) as model:
        for view, camera in views(model, *args.image).items():
            for shading in SHADINGS:
                reference = None
                for poe in POES:
                    model.render_complete(
                        camera, shading=shading, pixels_of_error=poe, ao_samples=args.ao_samples
                    )
                    ms, frame = frame_ms(
                        model,
                        camera,
                        args.repeats,
                        shading=shading,
                        pixels_of_error=poe,
                        ao_samples=args.ao_samples,
                    )
                    if reference is None:
                        reference = frame
                    s = frame.stats.as_dict()
                    rows.append(
                        {
                            "view": view,
                            "shading": shading,
                            "poe": poe,
                            "frame_ms": ms,
                            "mrays_s": s["rays"] / ms / 1e3,
                            "working_set_mib": s["working_set_bytes"] / 2**20,
                            "voxel_hits_pct": 100 * s["voxel_hits"] / max(1, s["rays"]),
                            "psnr_db": psnr(frame.image, reference.image),
                            "ssim": ssim(frame.image, reference.image),
                            "hit_differs_pct": 100 * float(np.mean(frame.prim != reference.prim)),
                        }
                    )
                    print(f"  {view} {shading} PoE {poe:g}: {ms:.0f} ms", file=sys.stderr, flush=True)
    return rows


def study_size(args: argparse.Namespace) -> list[dict[str, Any]]:
    rows = []
    for size in args.sizes:
        path = built_model(size)
        drop_page_cache(path)
        start = time.perf_counter()
        cache = make_cache(args.cache, 2)
        model = OutOfCoreModel(path, cache)
        opened = time.perf_counter()
        camera = frame_bounds(*model.bounds, width=args.image[0], height=args.image[1])
        first = model.render(camera, pixels_of_error=2.0)
        first_ms = 1000 * (time.perf_counter() - opened)
        row: dict[str, Any] = {
            "triangles": model.triangle_count,
            "file_mib": model.file_size / 2**20,
            "open_ms": 1000 * (opened - start),
            "first_frame_ms": first_ms,
            "first_frame_voxel_pct": 100 * first.stats.voxel_hits / first.stats.rays,
        }
        for poe, tag in ((2.0, "lod"), (0.0, "full")):
            try:
                done = model.render_complete(camera, pixels_of_error=poe)
            except CacheTooSmallError:
                row[f"{tag}_ms"] = math.nan
                continue
            row[f"{tag}_complete_s"] = done.seconds
            row[f"{tag}_frames"] = done.frames
            row[f"{tag}_working_set_mib"] = done.stats.working_set_bytes / 2**20
            row[f"{tag}_voxel_pct"] = 100 * done.stats.voxel_hits / done.stats.primary_rays
            for packets in (1, 4, 16):
                ms, _ = frame_ms(model, camera, args.repeats, pixels_of_error=poe, packets=packets)
                key = f"{tag}_ms" if packets == 1 else f"{tag}_packets{packets}_ms"
                row[key] = ms
            row[f"{tag}_fastest_ms"] = min(
                row[f"{tag}_ms"], row[f"{tag}_packets4_ms"], row[f"{tag}_packets16_ms"]
            )
            if tag == "lod":
                for shading in ("sun", "indirect"):
                    if shading not in SHADINGS:
                        continue
                    try:
                        model.render_complete(camera, pixels_of_error=poe, shading=shading)
                    except CacheTooSmallError:  # secondary rays reach more of the model
                        row[f"lod_{shading}_ms"] = math.nan
                        continue
                    row[f"lod_{shading}_ms"], _ = frame_ms(model, camera, args.repeats, pixels_of_error=poe,
                                                           shading=shading)  # fmt: skip
                row["lod_sun_over_headlight"] = row.get("lod_sun_ms", math.nan) / row["lod_fastest_ms"]
        model.close()
        if size <= args.incore_max:
            # The in-core renderer on the same tree (the model decoded whole), same camera,
            # same threads, in this process: the out-of-core full-detail ratio.
            with ModelFile(path) as f:
                scene = f.to_scene()
            scene.any_hit_stats()  # the wide BVH the primary rays walk, built before the clock
            cam = camera.to_native()
            for packets in (1, 16):
                frames = [trace(scene, cam, packets=packets) for _ in range(args.repeats)]
                row[f"incore_p{packets}_ms"] = statistics.median(f.stats.milliseconds for f in frames)
            # The kd-tree's packets, the out-of-core walk's in-core twin (the same tree).
            with mock.patch.dict(os.environ, {"VASTRAY_PRIMARY": "kd"}):
                frames = [trace(scene, cam, packets=16) for _ in range(args.repeats)]
            row["incore_kd_p16_ms"] = statistics.median(f.stats.milliseconds for f in frames)
            del scene
            for tag in ("p1", "p16", "kd_p16"):
                ooc = row.get("full_ms" if tag == "p1" else "full_packets16_ms", math.nan)
                row[f"full_{tag}_over_incore"] = row[f"incore_{tag}_ms"] / ooc
            row["full_fastest_over_incore_fastest"] = min(
                row["incore_p1_ms"], row["incore_p16_ms"]
            ) / row.get("full_fastest_ms", math.nan)
        rows.append(row)
        print(f"  {size:.0e}: {json.dumps(row)}", file=sys.stderr, flush=True)
    return rows


def study_pixels(args: argparse.Namespace) -> list[dict[str, Any]]:
    """Working set and time to complete of the overview against its pixel count."""
    path = built_model(args.pixels_size)
    rows = []
    for width, height in ((320, 180), (640, 360), (1280, 720), (1920, 1080)):
        drop_page_cache(path)
        cache = make_cache(args.cache, 2)
        with OutOfCoreModel(path, cache) as model:
            camera = frame_bounds(*model.bounds, width=width, height=height)
            try:
                done = model.render_complete(camera, pixels_of_error=2.0)
            except CacheTooSmallError:
                rows.append({"width": width, "height": height, "complete_s": math.nan})
                continue
            s = done.stats
            rows.append(
                {
                    "width": width,
                    "height": height,
                    "pixels": width * height,
                    "complete_s": done.seconds,
                    "frames": done.frames,
                    "working_set_mib": s.working_set_bytes / 2**20,
                    "working_set_bytes_per_pixel": s.working_set_bytes / (width * height),
                    "read_mib": cache.totals()["bytes_read"] / 2**20,
                    "voxel_hits_pct": 100 * s.voxel_hits / s.primary_rays,
                    "frame_ms": frame_ms(model, camera, args.repeats, pixels_of_error=2.0)[0],
                }
            )
        print(f"  {width}x{height}: {json.dumps(rows[-1])}", file=sys.stderr, flush=True)
    return rows


def study_loading(args: argparse.Namespace) -> list[dict[str, Any]]:
    path = built_model(args.loading_size)
    rows = []
    for budget in args.budgets:
        for fetchers in (1, 2, 4):
            for priority in ("count", "size"):
                drop_page_cache(path)
                cache = make_cache(budget, fetchers, priority)
                with OutOfCoreModel(path, cache) as model:
                    camera = frame_bounds(*model.bounds, width=args.image[0], height=args.image[1])
                    try:
                        done = model.render_complete(camera, pixels_of_error=2.0)
                        seconds, frames = done.seconds, done.frames
                    except CacheTooSmallError:
                        seconds, frames = math.nan, 0
                rows.append(
                    {
                        "budget_mib": budget >> 20,
                        "fetchers": fetchers,
                        "priority": priority,
                        "complete_s": seconds,
                        "frames": frames,
                    }
                )
                print(
                    f"  {budget >> 20} MiB, {fetchers} fetchers, {priority}: {seconds:.2f} s", file=sys.stderr
                )
    return rows


_OOC_CHILD = r"""
import json, math, sys, time
import numpy as np
from vastray.camera import Camera
from vastray.outofcore import OutOfCoreModel, make_cache
path = sys.argv[1]
budget, poe, frames = int(sys.argv[2]), float(sys.argv[3]), int(sys.argv[4])
width, height = int(sys.argv[5]), int(sys.argv[6])
def status():
    out = {}
    for line in open("/proc/self/status"):
        if line.startswith(("VmRSS", "VmHWM")):
            out[line.split(":")[0]] = int(line.split()[1]) / 1024
    return out
base = status()
cache = make_cache(budget, 2)
model = OutOfCoreModel(path, cache)
lo, hi = (np.asarray(v) for v in model.bounds)
centre, diag = (lo + hi) / 2, float(np.linalg.norm(hi - lo))
rows, start = [], time.perf_counter()
for i in range(frames):
    s = i / max(1, frames - 1)
    angle, dist = 0.3 + 1.2 * s, diag * (0.9 - 0.6 * s)  # orbit while flying in
    eye = centre + np.array([math.cos(angle) * 0.75, 0.45, math.sin(angle) * 0.75]) * dist
    camera = Camera(eye=tuple(eye), target=tuple(centre), width=width, height=height)
    f = model.render(camera, pixels_of_error=poe)
    st, s = status(), f.stats.as_dict()
    rows.append({"frame": i, "t_s": time.perf_counter() - start, "frame_ms": s["milliseconds"],
                 "complete": f.complete, "voxel_hits": s["voxel_hits"], "loaded": s["blocks_loaded"],
                 "evicted": s["blocks_evicted"], "pending": s["pending"],
                 "working_set_mib": s["working_set_bytes"] / 2**20,
                 "rss_mib": st["VmRSS"], "hwm_mib": st["VmHWM"]})
    cache.wait_for_fetches(50)
print(json.dumps({"base": base, "file_mib": model.file_size / 2**20, "rows": rows,
                  "bytes_read_mib": cache.totals()["bytes_read"] / 2**20}))
"""


def study_ooc(args: argparse.Namespace) -> tuple[list[dict[str, Any]], dict[str, Any]]:
    path = built_model(args.ooc_size)
    drop_page_cache(path)
    # A fresh process: its resident memory is the renderer's, not this script's.
    result = subprocess.run(
        [
            sys.executable,
            "-c",
            _OOC_CHILD,
            str(path),
            str(args.ooc_cache),
            "2",
            str(args.ooc_frames),
            str(args.image[0]),
            str(args.image[1]),
        ],
        capture_output=True,
        text=True,
        check=True,
    )
    out = json.loads(result.stdout)
    summary = {
        "file_mib": out["file_mib"],
        "cache_mib": args.ooc_cache >> 20,
        "file_over_cache": out["file_mib"] / (args.ooc_cache >> 20),
        "base_rss_mib": out["base"]["VmRSS"],
        "peak_rss_mib": max(r["hwm_mib"] for r in out["rows"]),
        "bytes_read_mib": out["bytes_read_mib"],
    }
    return out["rows"], summary


# ----------------------------------------------------------------------------- output


def study_projection(args: argparse.Namespace) -> list[dict[str, Any]]:
    rows = []
    for size in args.projection_sizes:
        path = built_model(size)
        with OutOfCoreModel(path, make_cache(args.cache, 2)) as model:
            for view in ("iso", "front", "top"):
                for projection in PROJECTIONS:
                    camera = frame_bounds(*model.bounds, width=args.image[0], height=args.image[1], view=view,
                                          projection=projection)  # fmt: skip
                    done = model.render_complete(camera, pixels_of_error=2.0)
                    hit = int((done.prim != -1).sum())
                    row: dict[str, Any] = {
                        "triangles": model.triangle_count,
                        "view": view,
                        "projection": projection,
                        "hit_pixels_pct": 100 * hit / done.prim.size,
                        "working_set_mib": done.stats.working_set_bytes / 2**20,
                        "voxel_hits_pct": 100 * done.stats.voxel_hits / max(1, hit),
                    }
                    for packets in (1, 16):
                        ms, _ = frame_ms(model, camera, args.repeats, pixels_of_error=2.0, packets=packets)
                        row[f"p{packets}_ms"] = ms
                        row[f"p{packets}_ns_per_hit_pixel"] = ms * 1e6 / max(1, hit)
                    rows.append(row)
                    print(f"  {size:.0e} {view} {projection}: {row['p16_ms']:.0f} ms", file=sys.stderr)
    return rows


def plot_projection(rows: list[dict[str, Any]], out: Path) -> None:
    plt = pyplot()
    if plt is None:
        return

    fig, axes = plt.subplots(1, 2, figsize=(12, 4.5))
    first = [r for r in rows if r["projection"] == PROJECTIONS[0]]
    labels = [f"1e{round(math.log10(r['triangles']))} {r['view']}" for r in first]
    x = np.arange(len(labels))
    for k, projection in enumerate(PROJECTIONS):
        sel = [r for r in rows if r["projection"] == projection]
        axes[0].bar(x + 0.4 * k, [r["p16_ms"] for r in sel], 0.4, label=projection)
        axes[1].bar(x + 0.4 * k, [r["p16_ns_per_hit_pixel"] for r in sel], 0.4, label=projection)
    for ax, ylabel in zip(axes, ("frame time, 4x4 packets (ms)", "ns per pixel that hits"), strict=True):
        ax.set_xticks(x + 0.2, labels, rotation=30)
        ax.set_ylabel(ylabel)
        ax.legend()
    save_figure(fig, "Orthographic against perspective views (PoE 2)", out / "tradeoff-projection.png")


def write(name: str, rows: list[dict[str, Any]], out: Path, note: str = "") -> str:
    out.mkdir(parents=True, exist_ok=True)
    headers = list(rows[0].keys())
    with open(out / f"{name}.csv", "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=headers)
        writer.writeheader()
        writer.writerows(rows)
    table = markdown_table(headers, [[_cell(r.get(h)) for h in headers] for r in rows])
    (out / f"{name}.md").write_text(f"# {name}\n\n{note}\n\n{table}\n")
    return table


def _cell(v: Any) -> Any:
    if isinstance(v, float):
        return "n/a" if math.isnan(v) else (f"{v:.3g}" if abs(v) < 100 else f"{v:.0f}")
    return v


def plot_poe(rows: list[dict[str, Any]], out: Path) -> None:
    plt = pyplot()
    if plt is None:
        return

    fig, axes = plt.subplots(1, 3, figsize=(15, 4.5))
    for shading in SHADINGS:
        sel = [r for r in rows if r["shading"] == shading and r["view"] == "overview"]
        poe = [max(r["poe"], 0.25) for r in sel]
        axes[0].plot(poe, [r["frame_ms"] for r in sel], "o-", label=shading)
        axes[1].plot(poe, [r["hit_differs_pct"] for r in sel], "o-", label=shading)
        axes[2].plot(poe, [min(r["psnr_db"], 80) for r in sel], "o-", label=shading)
    labels = ("frame time (ms)", "pixels whose hit differs (%)", "PSNR (dB, capped at 80)")
    for ax, ylabel in zip(axes, labels, strict=True):
        ax.set_xscale("log")
        ax.set_xlabel("pixels of error (PoE 0 drawn at 0.25)")
        ax.set_ylabel(ylabel)
        ax.legend()
    save_figure(fig, "Speed against accuracy (overview view)", out / "tradeoff-poe.png")


def plot_size(rows: list[dict[str, Any]], out: Path) -> None:
    plt = pyplot()
    if plt is None:
        return

    fig, ax = plt.subplots(figsize=(7, 4.5))
    tris = [r["triangles"] for r in rows]
    ax.plot(tris, [r.get("lod_ms", math.nan) for r in rows], "o-", label="LOD, PoE 2")
    ax.plot(tris, [r.get("full_ms", math.nan) for r in rows], "s-", label="full detail, PoE 0")
    ax.plot(tris, [r["first_frame_ms"] for r in rows], "^-", label="first frame after open")
    ax.set_xscale("log")
    ax.set_xlabel("triangles")
    ax.set_ylabel("frame time (ms)")
    ax.legend()
    save_figure(fig, "Frame time against model size (paper 000 Fig. 7)", out / "tradeoff-size.png")


def plot_ooc(rows: list[dict[str, Any]], summary: dict[str, Any], out: Path) -> None:
    plt = pyplot()
    if plt is None:
        return

    fig, ax = plt.subplots(figsize=(7, 4.5))
    t = [r["t_s"] for r in rows]
    ax.plot(t, [r["rss_mib"] for r in rows], label="resident memory (MiB)")
    ax.axhline(summary["cache_mib"], color="grey", linestyle="--", label="cache budget")
    ax.plot(t, [r["frame_ms"] for r in rows], label="frame time (ms)")
    ax.set_xlabel("seconds along the camera path")
    ax.legend()
    save_figure(
        fig,
        f"{summary['file_mib']:.0f} MiB model through a {summary['cache_mib']} MiB cache",
        out / "tradeoff-ooc.png",
    )


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--studies", default="poe,size,pixels,loading,ooc,projection")
    p.add_argument("--isa", default=None, help="force the kernels' ISA path (VASTRAY_ISA)")
    p.add_argument("--incore-max", type=float, default=1e7, help="largest model also rendered in core")
    p.add_argument("--pixels-size", type=float, default=1e8, help="model of the pixels study")
    p.add_argument("--image", default="1280x720", help="frame size WxH")
    p.add_argument("--poe-image", default="640x360", help="frame size of the PoE study (AO is slow)")
    p.add_argument("--study-size", type=float, default=1e6, help="model size of the PoE study")
    p.add_argument("--sizes", default="1e5,1e6,1e7,1e8", help="model sizes of the size study")
    p.add_argument("--loading-size", type=float, default=1e7)
    p.add_argument("--projection-sizes", default="1e7,1e8", help="model sizes of the projection study")
    p.add_argument("--budgets", default="256M,512M,1G")
    p.add_argument("--ooc-size", type=float, default=1e8)
    p.add_argument("--ooc-cache", default="512M")
    p.add_argument("--ooc-frames", type=int, default=40)
    p.add_argument("--cache", default="3G", help="cache budget of the PoE and size studies")
    p.add_argument("--ao-samples", type=int, default=4)
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--out", type=Path, default=RESULTS_DIR)
    args = p.parse_args()
    if args.isa:
        os.environ["VASTRAY_ISA"] = args.isa  # read when the first ray is traced
    args.sizes = [int(float(s)) for s in args.sizes.split(",")]
    args.projection_sizes = [int(float(s)) for s in args.projection_sizes.split(",")]
    args.study_size, args.loading_size, args.ooc_size = (
        int(args.study_size),
        int(args.loading_size),
        int(args.ooc_size),
    )
    args.incore_max, args.pixels_size = int(args.incore_max), int(args.pixels_size)
    args.budgets = [parse_bytes(b) for b in args.budgets.split(",")]
    args.ooc_cache, args.cache = parse_bytes(args.ooc_cache), parse_bytes(args.cache)
    size_image = tuple(int(v) for v in args.image.split("x"))
    studies = args.studies.split(",")
    info = machine_info()
    header = f"{info['cpu']}, {info['logical cores']} cores, ISA path {isa_path()}, revision {info['git']}"

    if "poe" in studies:
        args.image = tuple(int(v) for v in args.poe_image.split("x"))
        rows = study_poe(args)
        print(
            write(
                "tradeoff-poe",
                rows,
                args.out,
                f"{header}; plant 1e{round(math.log10(args.study_size))}, "
                f"{args.poe_image}, every frame complete at its PoE; error against the PoE 0 image",
            )
        )
        plot_poe(rows, args.out)
    args.image = size_image
    if "size" in studies:
        rows = study_size(args)
        print(
            write(
                "tradeoff-size",
                rows,
                args.out,
                f"{header}; plant, {args.image[0]}x{args.image[1]} headlight, "
                "overview, single rays unless packets are named; page cache dropped before opening; "
                "incore_*: the in-core renderer on the same model decoded whole (its primary rays "
                "through the wide BVH; incore_kd_p16: through the kd-tree, as out of core), *_over_incore: "
                "its frame time over the out-of-core full-detail one (above 1: out of core is faster)",
            )
        )
        plot_size(rows, args.out)
    if "pixels" in studies:
        rows = study_pixels(args)
        print(
            write(
                "tradeoff-pixels",
                rows,
                args.out,
                f"{header}; plant 1e{round(math.log10(args.pixels_size))}, overview at PoE 2, headlight, "
                "cold (page cache dropped), each size in a fresh cache: working set against pixels",
            )
        )
    if "loading" in studies:
        rows = study_loading(args)
        print(
            write(
                "tradeoff-loading",
                rows,
                args.out,
                f"{header}; plant 1e{round(math.log10(args.loading_size))}, "
                "overview at PoE 2 from a cold start; page cache dropped before each run",
            )
        )
    if "ooc" in studies:
        rows, summary = study_ooc(args)
        note = f"{header}; " + ", ".join(f"{k} {_cell(v)}" for k, v in summary.items())
        print(note)
        print(write("tradeoff-ooc", rows, args.out, note))
        plot_ooc(rows, summary, args.out)
    if "projection" in studies:
        rows = study_projection(args)
        print(
            write(
                "tradeoff-projection",
                rows,
                args.out,
                f"{header}; plant, {args.image[0]}x{args.image[1]} headlight at PoE 2, each view framed "
                "whole (frame_bounds), complete; p1: single rays, p16: 4x4 packets (median of "
                f"{args.repeats} frames); *_ns_per_hit_pixel: frame time over the pixels that show the model",
            )
        )
        plot_projection(rows, args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
