"""Rays per second of the vastray kd-tree against Embree, on the same rays, side by side.

For every real mesh in ../shared/models ($VASTRAY_MODELS) and for procedural scenes
(plant, mandelbulb) of 10^5, 10^6 and 10^7 triangles this measures

* build: wall time, triangles/s, kd-tree nodes and bytes, and the peak-RSS growth of
  the process during the build (and the same for Embree's BVH build);
* primary rays of a camera framing the model (1024x768 by default): vastray's renderer
  (shading='normal', its own clock), vastray's batch `intersect` and Embree's `run`
  (rtcIntersect1 per ray, via embreex) on the very same rays;
* ambient-occlusion rays: 8 cosine-weighted directions about the facing normal of every
  primary hit, length 0.2 x the scene diagonal: vastray `occluded` against Embree's
  occlusion query;
* shadow rays: one from each AO origin along one direction (a distant light), unbounded,
  the same way;

each on one thread and on all hardware threads, best of N runs, with vastray and Embree
interleaved in the same loop so a busy machine slows both alike. The key number is
the ratio vastray / Embree rays/s on one thread. Writes rays.md, rays.csv and rays.png
to bench/results/.

    python bench/rays.py              # full set (about 10-15 minutes on 2 cores)
    python bench/rays.py --quick      # smoke run, a minute
    python bench/rays.py --models bunny,plant --sizes 1e5,1e6
"""

from __future__ import annotations

import argparse
import csv
import gc
import math
import os
import sys
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from common import (  # bench/ is a folder of scripts, not a package
    RESULTS_DIR,
    Best,
    PeakRss,
    ao_rays_from_hits,
    camera_rays,
    fmt,
    format_count,
    geometric_mean,
    machine_info,
    markdown_table,
    models_dir,
    parse_count,
    pin_native,
    pyplot,
    save_figure,
    shadow_rays_from,
    timed,
)

# The kernels' ISA path is chosen when the first ray is traced: --isa sets VASTRAY_ISA.
if "--isa" in sys.argv[:-1]:
    os.environ["VASTRAY_ISA"] = sys.argv[sys.argv.index("--isa") + 1]
# Pin one build of the extension for the whole run (others may rebuild it meanwhile).
NATIVE_BUILD = pin_native() if "--no-pin" not in sys.argv else "as installed (--no-pin)"

from vastray import native  # noqa: E402
from vastray.camera import frame_bounds  # noqa: E402
from vastray.ingest import load_mesh  # noqa: E402
from vastray.mesh import Mesh  # noqa: E402
from vastray.renderer import trace  # noqa: E402

PROCEDURAL = ("plant", "mandelbulb")
MESH_SUFFIXES = (".obj", ".ply", ".stl", ".off", ".glb", ".gltf")
MB = 1e6


# ----------------------------------------------------------------------------- models


@dataclass(frozen=True)
class ModelSpec:
    label: str
    path: Path | None = None  # a mesh file, or
    generator: str | None = None  # a procedural scene name ...
    triangles: int = 0  # ... and its size

    def load(self, seed: int) -> Mesh:
        if self.path is not None:
            return load_mesh(self.path)
        try:
            from vastray.scenes import to_mesh
        except ImportError as exc:
            raise SystemExit(f"vastray.scenes is not available ({exc}); cannot make {self.label}") from exc
        assert self.generator is not None
        return to_mesh(self.generator, self.triangles, seed)


def select_models(names: list[str], sizes: list[int]) -> list[ModelSpec]:
    """Model names are mesh file stems (or unique prefixes of them), 'plant', 'mandelbulb',
    or the groups 'real', 'procedural' and 'all'."""
    folder = models_dir()
    files = []
    if folder.is_dir():
        files = sorted(p for p in folder.iterdir() if p.suffix.lower() in MESH_SUFFIXES)
    specs: list[ModelSpec] = []

    def add(spec: ModelSpec) -> None:
        if spec not in specs:
            specs.append(spec)

    for name in names:
        if name in ("all", "real"):
            if not files:
                print(f"warning: no meshes in {folder} (set VASTRAY_MODELS)", file=sys.stderr)
            for p in files:
                add(ModelSpec(label=p.stem, path=p))
        if name in ("all", "procedural"):
            for gen in PROCEDURAL:
                for n in sizes:
                    add(ModelSpec(label=f"{gen}-{format_count(n)}", generator=gen, triangles=n))
        if name in ("all", "real", "procedural"):
            continue
        if name in PROCEDURAL:
            for n in sizes:
                add(ModelSpec(label=f"{name}-{format_count(n)}", generator=name, triangles=n))
            continue
        matches = [p for p in files if p.stem == name] or [p for p in files if p.stem.startswith(name)]
        if len(matches) != 1:
            known = ", ".join([p.stem for p in files] + list(PROCEDURAL))
            raise SystemExit(f"unknown or ambiguous model {name!r} (known: {known})")
        add(ModelSpec(label=matches[0].stem, path=matches[0]))
    # Real meshes first, then procedural by size so memory high-water marks grow in order.
    return sorted(specs, key=lambda s: (s.path is None, s.triangles, s.label))


# ----------------------------------------------------------------------------- Embree


class EmbreeTracer:
    """Embree through embreex: one rtcIntersect1 / rtcOccluded1 per ray in a C loop on the
    calling thread; embreex releases the GIL there, so all-thread runs split the rays into
    chunks over a thread pool (dynamic load balancing, like vastray's 1024-ray batches)."""

    def __init__(self, vertices: np.ndarray, faces: np.ndarray, pool: ThreadPoolExecutor) -> None:
        from embreex import rtcore_scene as rtcs
        from embreex.mesh_construction import TriangleMesh

        self.pool = pool
        self.scene = rtcs.EmbreeScene()
        TriangleMesh(self.scene, np.ascontiguousarray(vertices[faces], dtype=np.float32))
        # embreex commits (builds the BVH) lazily on the first query: force it now.
        probe = np.zeros((1, 3), dtype=np.float32)
        self.scene.run(probe, np.array([[0.0, 0.0, 1.0]], dtype=np.float32))

    def _chunks(self, n: int, threads: int) -> list[slice]:
        size = max(2048, min(16384, n // max(1, threads * 32)))
        return [slice(i, min(n, i + size)) for i in range(0, n, size)]

    def intersect(self, o: np.ndarray, d: np.ndarray, threads: int) -> tuple[np.ndarray, np.ndarray]:
        """(prim (-1 on a miss), t) of the closest hits."""
        n = o.shape[0]
        if threads <= 1:
            r = self.scene.run(o, d, output=1)
            return r["primID"], r["tfar"]
        prim = np.empty(n, dtype=np.int32)
        tfar = np.empty(n, dtype=np.float32)

        def work(s: slice) -> None:
            r = self.scene.run(o[s], d[s], output=1)
            prim[s] = r["primID"]
            tfar[s] = r["tfar"]

        list(self.pool.map(work, self._chunks(n, threads)))
        return prim, tfar

    def occluded(self, o: np.ndarray, d: np.ndarray, tmax: np.ndarray, threads: int) -> np.ndarray:
        """Any hit in [0, tmax] per ray."""
        n = o.shape[0]
        if threads <= 1:
            return self.scene.run(o, d, dists=tmax.copy(), query="OCCLUDED") != -1
        out = np.empty(n, dtype=bool)

        def work(s: slice) -> None:
            out[s] = self.scene.run(o[s], d[s], dists=tmax[s].copy(), query="OCCLUDED") != -1

        list(self.pool.map(work, self._chunks(n, threads)))
        return out


def embree_version() -> str | None:
    try:
        from importlib.metadata import version

        return version("embreex")
    except Exception:
        return None


# ----------------------------------------------------------------------------- measuring


@dataclass
class Timings:
    """Best-of-N seconds per (engine, thread setting)."""

    runs: dict[str, Best] = field(default_factory=dict)

    def add(self, key: str, seconds: float) -> None:
        self.runs.setdefault(key, Best()).add(seconds)

    def rate(self, key: str, rays: int) -> float:
        """Million rays per second from the best run."""
        best = self.runs[key].best if key in self.runs else math.nan
        return rays / best / MB if best > 0 else math.nan


def interleave(
    reps: int, steps: list[tuple[str, Callable[[], Any]]], timings: Timings, min_time: float = 0.0
) -> dict[str, Any]:
    """Run every step `reps` times, alternating the order each repetition so neither side
    always runs first; keeps the best time per step and the last result of each. Cheap
    steps get extra repetitions (up to 4 x reps) until the group has run `min_time` s."""
    last: dict[str, Any] = {}
    start = time.perf_counter()
    rep = 0
    while rep < reps or (time.perf_counter() - start < min_time and rep < 4 * reps):
        order = steps if rep % 2 == 0 else steps[::-1]
        for key, fn in order:
            seconds, result = fn()
            timings.add(key, seconds)
            last[key] = result
        rep += 1
    return last


def wall(fn: Callable[[], Any]) -> Callable[[], tuple[float, Any]]:
    return lambda: timed(fn)


def measure_occlusion(
    key: str,
    scene: Any,
    embree: Any,
    origins: np.ndarray,
    dirs: np.ndarray,
    tmax: float,
    args: argparse.Namespace,
    thread_settings: list[tuple[str, int]],
) -> dict[str, Any]:
    """Any-hit rays through vastray's `occluded` and Embree's occlusion query, interleaved:
    the fields KEY_1T/KEY_NT (Mrays/s), eKEY_* (Embree's), ratio_KEY_*, KEY_rays,
    KEY_runs, KEY_occluded_pct and KEY_agree_pct of a result row."""
    o32, d32 = origins.astype(np.float32), dirs.astype(np.float32)
    tmax32 = np.full(origins.shape[0], tmax, dtype=np.float32)
    n = origins.shape[0]
    steps = []
    for tag, threads in thread_settings:
        steps.append((f"v_{tag}", wall(lambda t=threads: scene.occluded(origins, dirs, 0, tmax, threads=t))))
        if embree is not None:
            steps.append((f"e_{tag}", wall(lambda t=threads, e=embree: e.occluded(o32, d32, tmax32, t))))
    timings = Timings()
    last = interleave(args.ao_reps, steps, timings, args.min_time)
    ours = np.asarray(last["v_1t"], dtype=bool)
    out: dict[str, Any] = {
        f"{key}_runs": len(timings.runs["v_1t"].values),
        f"{key}_rays": n,
        f"{key}_occluded_pct": 100.0 * float(ours.mean()) if n else math.nan,
    }
    for tag, _ in thread_settings:
        out[f"{key}_{tag}"] = timings.rate(f"v_{tag}", n)
        out[f"e{key}_{tag}"] = timings.rate(f"e_{tag}", n) if embree else math.nan
        out[f"ratio_{key}_{tag}"] = out[f"{key}_{tag}"] / out[f"e{key}_{tag}"]
    if embree is not None and n:
        out[f"{key}_agree_pct"] = 100.0 * float(np.mean(np.asarray(last["e_1t"], dtype=bool) == ours))
    print(
        f"   {key} ({n:,} rays) 1T Mrays/s: vastray {out[f'{key}_1t']:.2f}  "
        f"Embree {out[f'e{key}_1t']:.2f} | "
        f"all: vastray {out[f'{key}_nt']:.2f}  Embree {out[f'e{key}_nt']:.2f} | "
        f"agree {out.get(f'{key}_agree_pct', math.nan):.3f}%",
        flush=True,
    )
    return out


def bench_model(
    spec: ModelSpec, args: argparse.Namespace, pool: ThreadPoolExecutor | None, all_threads: int
) -> dict[str, Any]:
    row: dict[str, Any] = {"model": spec.label}
    print(f"\n== {spec.label}", flush=True)
    gen_s, mesh = timed(lambda: spec.load(args.seed))
    tris = mesh.triangle_count
    row.update(triangles=tris, load_s=gen_s)
    print(f"   {tris:,} triangles, loaded/generated in {gen_s:.2f} s", flush=True)

    vertices = np.ascontiguousarray(mesh.vertices, dtype=np.float64)
    faces = np.ascontiguousarray(mesh.faces, dtype=np.uint32)
    del mesh
    gc.collect()

    # --- builds (vastray first, before Embree's buffers exist)
    def scene_with_kd_tree() -> native.Scene:
        scene = native.Scene(vertices, faces, threads=0)
        _ = scene.build_stats  # the kd-tree is built on first use: here, timed
        return scene

    with PeakRss() as mem:
        build_s, scene = timed(scene_with_kd_tree)
    st = scene.build_stats
    row.update(
        build_s=build_s,
        build_mtris_s=tris / build_s / MB,
        kd_nodes=int(st["nodes"]),
        kd_leaves=int(st["leaves"]),
        kd_refs_per_tri=st["references"] / tris,
        kd_depth=int(st["max_depth"]),
        kd_mb=st["memory_bytes"] / MB,
        build_rss_mb=mem.delta / MB,
    )
    print(
        f"   vastray build {build_s:.2f} s ({tris / build_s / MB:.2f} Mtri/s), {st['nodes']:,} nodes, "
        f"{st['memory_bytes'] / MB:.1f} MB, peak RSS +{mem.delta / MB:.0f} MB",
        flush=True,
    )
    # The wide BVH of any-hit rays is built on first use; build it here, timed, so the
    # occlusion timings below compare structures that are both built.
    with PeakRss() as amem:
        any_s, any_hit = timed(scene.any_hit_stats)
    row.update(
        anyhit_build_s=any_s, anyhit_mb=any_hit.get("memory_bytes", 0) / MB, anyhit_rss_mb=amem.delta / MB
    )
    print(
        f"   any-hit {any_hit['structure']} build {any_s:.2f} s, {any_hit.get('nodes', 0):,} nodes, "
        f"{row['anyhit_mb']:.1f} MB, peak RSS +{amem.delta / MB:.0f} MB",
        flush=True,
    )
    embree: EmbreeTracer | None = None
    if pool is not None:
        with PeakRss() as emem:
            ebuild_s, embree = timed(lambda: EmbreeTracer(vertices, faces, pool))
        row.update(embree_build_s=ebuild_s, embree_rss_mb=emem.delta / MB)
        print(f"   Embree build {ebuild_s:.2f} s, peak RSS +{emem.delta / MB:.0f} MB", flush=True)

    # --- primary rays
    lo, hi = (np.asarray(b, dtype=np.float64) for b in scene.bounds)
    diagonal = float(np.linalg.norm(hi - lo))
    cam = frame_bounds(lo, hi, fov=args.fov, width=args.width, height=args.height)
    origins, dirs = camera_rays(cam.eye, cam.target, cam.up, cam.fov, cam.width, cam.height)
    o32, d32 = origins.astype(np.float32), dirs.astype(np.float32)
    n_primary = origins.shape[0]
    thread_settings = [("1t", 1), ("nt", all_threads)]

    def render(threads: int) -> tuple[float, Any]:
        frame = trace(scene, cam, shading="normal", threads=threads)
        return frame.stats.milliseconds / 1e3, frame

    steps: list[tuple[str, Callable[[], tuple[float, Any]]]] = []
    for tag, threads in thread_settings:
        steps.append((f"render_{tag}", lambda t=threads: render(t)))  # type: ignore[misc]
        steps.append((f"batch_{tag}", wall(lambda t=threads: scene.intersect(origins, dirs, threads=t))))
        if embree is not None:
            steps.append((f"embree_{tag}", wall(lambda t=threads, e=embree: e.intersect(o32, d32, t))))
    prim_t = Timings()
    last = interleave(args.reps, steps, prim_t, args.min_time)

    batch = last["batch_1t"]
    last_primary_stats = last["render_1t"].stats.as_dict()
    row["primary_runs"] = len(prim_t.runs["batch_1t"].values)
    vprim = np.asarray(batch["prim"], dtype=np.int64)
    hit = vprim >= 0
    frame_prim = np.asarray(last["render_1t"].prim).reshape(-1).astype(np.int64)
    row.update(
        primary_rays=n_primary,
        hit_pct=100.0 * hit.mean(),
        nodes_per_ray=batch["node_visits"] / n_primary,
        tris_per_ray=batch["triangle_tests"] / n_primary,
        render_vs_batch_prim_pct=100.0 * float(np.mean(np.where(frame_prim < 0, -1, frame_prim) == vprim)),
    )
    for tag, _ in thread_settings:
        row[f"render_{tag}"] = prim_t.rate(f"render_{tag}", n_primary)
        row[f"batch_{tag}"] = prim_t.rate(f"batch_{tag}", n_primary)
        row[f"embree_{tag}"] = prim_t.rate(f"embree_{tag}", n_primary) if embree else math.nan
    if embree is not None:
        eprim = np.asarray(last["embree_1t"][0], dtype=np.int64)
        row["agree_hit_pct"] = 100.0 * float(np.mean((eprim >= 0) == hit))
        row["agree_prim_pct"] = 100.0 * float(np.mean(eprim == vprim))
    print(
        f"   primary 1T Mrays/s: render {row['render_1t']:.2f}  batch {row['batch_1t']:.2f}  "
        f"Embree {row.get('embree_1t', math.nan):.2f} | all: render {row['render_nt']:.2f}  "
        f"batch {row['batch_nt']:.2f}  Embree {row.get('embree_nt', math.nan):.2f} | "
        f"agree {row.get('agree_prim_pct', math.nan):.3f}%",
        flush=True,
    )

    # --- ambient-occlusion rays from the primary hits
    rng = np.random.default_rng(args.seed)
    ao_origins, ao_dirs, ao_tmax = ao_rays_from_hits(
        vertices, faces, dirs, batch, args.ao_samples, rng, diagonal
    )
    occlusion = partial(
        measure_occlusion, scene=scene, embree=embree, args=args, thread_settings=thread_settings
    )
    row.update(occlusion("ao", origins=ao_origins, dirs=ao_dirs, tmax=ao_tmax))
    # --- shadow rays: one from each AO origin (a hit point pushed off its surface) towards
    # one distant light, the rays of a `sun` view; Scene.occluded takes runs of them as
    # packets, as it does the AO rays of a point.
    sh_origins, sh_dirs = shadow_rays_from(ao_origins, args.ao_samples)
    row.update(occlusion("shadow", origins=sh_origins, dirs=sh_dirs, tmax=np.inf))
    # Traversal cost of AO rays as the renderer shoots them (its own sampling, skipping the
    # start triangle): wide-BVH node visits and triangle tests per AO ray. Not timed.
    ao_frame = trace(scene, cam, shading="ao", ao_samples=args.ao_samples, threads=0).stats.as_dict()
    primary_stats = last_primary_stats
    secondary = max(1, int(ao_frame["secondary_rays"]))
    row["ao_nodes_per_ray"] = (ao_frame["node_visits"] - primary_stats["node_visits"]) / secondary
    row["ao_tris_per_ray"] = (ao_frame["triangle_tests"] - primary_stats["triangle_tests"]) / secondary
    for tag, _ in thread_settings:
        row[f"ratio_batch_{tag}"] = row[f"batch_{tag}"] / row[f"embree_{tag}"]
        row[f"ratio_render_{tag}"] = row[f"render_{tag}"] / row[f"embree_{tag}"]
    return row


# ----------------------------------------------------------------------------- report


def isa_path() -> str:
    """The ISA path the kernels run on ('sse2', 'avx', 'avx2', 'avx512'; 'sse2 only' before issue 12)."""
    return native.isa() if hasattr(native, "isa") else "sse2 (no dispatch)"


def ratio(x: float) -> str:
    return "n/a" if not math.isfinite(x) else f"{x:.2f}x"


def occlusion_table(rows: list[dict[str, Any]], key: str, rays: str, nt: int, per_ray: bool = False) -> str:
    """The table of measure_occlusion's fields `key` (with the renderer's node visits and
    triangle tests per ray where `per_ray`)."""
    counts = ["nodes/ray", "tris/ray"] if per_ray else []
    headers = ["model", rays, "occluded %", "vastray 1T", "Embree 1T", "**ratio 1T**"]
    headers += [f"vastray {nt}T", f"Embree {nt}T", f"ratio {nt}T", *counts, "agree %"]
    table = []
    for r in rows:
        line = [r["model"], f"{r[f'{key}_rays']:,}", fmt(r[f"{key}_occluded_pct"], 1), fmt(r[f"{key}_1t"])]
        line += [fmt(r.get(f"e{key}_1t", math.nan)), "**" + ratio(r.get(f"ratio_{key}_1t", math.nan)) + "**"]
        line += [fmt(r[f"{key}_nt"]), fmt(r.get(f"e{key}_nt", math.nan))]
        line += [ratio(r.get(f"ratio_{key}_nt", math.nan))]
        if per_ray:
            line += [fmt(r[f"{key}_nodes_per_ray"], 1), fmt(r[f"{key}_tris_per_ray"], 1)]
        table.append([*line, fmt(r.get(f"{key}_agree_pct", math.nan), 3)])
    return markdown_table(headers, table)


def report(rows: list[dict[str, Any]], info: dict[str, str], args: argparse.Namespace, nt: int) -> str:
    res = f"{args.width}x{args.height}"
    parts = [
        "# vastray vs Embree: rays per second",
        "",
        f"vastray kernels on the **{isa_path()}** path. "
        "Same rays through both engines in one process, interleaved, best of at least "
        f"{args.reps} (primary) / {args.ao_reps} (AO and shadow) runs (cheap ones repeated for "
        f"{args.min_time:g} s). Mrays/s = million rays per second. "
        f"1T = one thread; {nt}T = all {nt} hardware threads. Ratios are vastray / Embree "
        "(above 1: vastray faster). The machine is shared and noisy: read the ratios, "
        "not the absolute rates.",
        "",
        "## Machine",
        "",
        *[f"- {k}: {v}" for k, v in info.items()],
        "",
        "## Summary",
        "",
    ]
    ok = [r for r in rows if math.isfinite(r.get("ratio_batch_1t", math.nan))]
    if ok:
        parts += [
            markdown_table(
                [f"ratio vastray ({isa_path()}) / Embree (geometric mean over models)", "1T", f"{nt}T"],
                [
                    [
                        "primary rays, batch intersect vs rtcIntersect1",
                        ratio(geometric_mean(r["ratio_batch_1t"] for r in ok)),
                        ratio(geometric_mean(r["ratio_batch_nt"] for r in ok)),
                    ],
                    [
                        "primary rays, renderer vs rtcIntersect1",
                        ratio(geometric_mean(r["ratio_render_1t"] for r in ok)),
                        ratio(geometric_mean(r["ratio_render_nt"] for r in ok)),
                    ],
                    [
                        "AO rays, occluded vs rtcOccluded1",
                        ratio(geometric_mean(r["ratio_ao_1t"] for r in ok)),
                        ratio(geometric_mean(r["ratio_ao_nt"] for r in ok)),
                    ],
                    [
                        "shadow rays (one direction), occluded vs rtcOccluded1",
                        ratio(geometric_mean(r["ratio_shadow_1t"] for r in ok)),
                        ratio(geometric_mean(r["ratio_shadow_nt"] for r in ok)),
                    ],
                ],
            ),
            "",
            "Worst single-thread primary ratio (batch): "
            + ", ".join(
                f"{r['model']} {ratio(r['ratio_batch_1t'])}"
                for r in sorted(ok, key=lambda r: r["ratio_batch_1t"])[:3]
            ),
            "",
        ]
    else:
        parts += ["Embree not measured (embreex missing or --no-embree).", ""]
    parts += [
        f"## Primary rays ({res}, camera framing the model, Mrays/s)",
        "",
        markdown_table(
            [
                "model",
                "triangles",
                "hit %",
                "render 1T",
                "batch 1T",
                "Embree 1T",
                "**ratio 1T**",
                "ratio render 1T",
                f"batch {nt}T",
                f"Embree {nt}T",
                f"ratio {nt}T",
                "nodes/ray",
                "tris/ray",
                "agree prim %",
            ],
            [
                [
                    r["model"],
                    f"{r['triangles']:,}",
                    fmt(r["hit_pct"], 1),
                    fmt(r["render_1t"]),
                    fmt(r["batch_1t"]),
                    fmt(r.get("embree_1t", math.nan)),
                    "**" + ratio(r.get("ratio_batch_1t", math.nan)) + "**",
                    ratio(r.get("ratio_render_1t", math.nan)),
                    fmt(r["batch_nt"]),
                    fmt(r.get("embree_nt", math.nan)),
                    ratio(r.get("ratio_batch_nt", math.nan)),
                    fmt(r["nodes_per_ray"], 1),
                    fmt(r["tris_per_ray"], 1),
                    fmt(r.get("agree_prim_pct", math.nan), 3),
                ]
                for r in rows
            ],
        ),
        "",
        f"## Ambient-occlusion rays ({args.ao_samples} per primary hit, tmax = 0.2 x diagonal, Mrays/s)",
        "",
        occlusion_table(rows, "ao", "AO rays", nt, per_ray=True),
        "",
        "## Shadow rays (one from each AO origin, along one direction to a distant light, Mrays/s)",
        "",
        occlusion_table(rows, "shadow", "shadow rays", nt),
        "",
        f"## Build ({nt} threads)",
        "",
        markdown_table(
            [
                "model",
                "triangles",
                "load/gen s",
                "build s",
                "Mtri/s",
                "kd nodes",
                "refs/tri",
                "depth",
                "kd MB",
                "peak RSS +MB",
                "any-hit BVH s",
                "any-hit MB",
                "Embree build s",
                "Embree RSS +MB",
            ],
            [
                [
                    r["model"],
                    f"{r['triangles']:,}",
                    fmt(r["load_s"]),
                    fmt(r["build_s"], 3),
                    fmt(r["build_mtris_s"]),
                    f"{r['kd_nodes']:,}",
                    fmt(r["kd_refs_per_tri"]),
                    str(r["kd_depth"]),
                    fmt(r["kd_mb"], 1),
                    fmt(r["build_rss_mb"], 0),
                    fmt(r.get("anyhit_build_s", math.nan), 3),
                    fmt(r.get("anyhit_mb", math.nan), 1),
                    fmt(r.get("embree_build_s", math.nan), 3),
                    fmt(r.get("embree_rss_mb", math.nan), 0),
                ]
                for r in rows
            ],
        ),
        "",
        "Columns: *render* = vastray's tiled renderer, shading='normal', timed by its own clock (ray "
        "generation + trace + shading, no Python); *batch* = `Scene.intersect` on the numpy rays "
        "(float64 in, t/prim/u/v out), wall time; *Embree* = embreex `run(output=1)`, one "
        "rtcIntersect1 per ray on float32 copies of the same rays (t/prim/u/v/Ng out), wall time; "
        "all-thread Embree splits the rays into chunks over a Python thread pool (embreex releases "
        "the GIL). *ratio* = batch / Embree. *nodes/ray*, *tris/ray* = vastray node visits (of a "
        "packet, counted once) and triangle tests per primary ray, through the 8-wide BVH since 7 "
        "December (the kd-tree before, or with VASTRAY_PRIMARY=kd; in the AO table: wide-BVH node "
        "visits and triangle tests per AO ray of the renderer's `ao` shading, not timed). "
        "*agree prim %* = rays where both "
        "engines report the same triangle (or both miss). *peak RSS +MB* = growth of the process's "
        "peak resident memory during the build (small builds reuse heap freed by earlier models and "
        "can show 0; Embree's includes the float32 triangle copy embreex hands it). The renderer "
        "traces 4x4 SIMD packets, `Scene.intersect` 16 neighbours of a row (one origin, one direction"
        " octant) as one packet (since 6 December; single rays before), all with the single-ray "
        "answers; since 7 December both walk the wide BVH (its packets: interval bounds, then each "
        "ray's own box test), and a hit at the same t as another goes to the lower triangle index. "
        "`Scene.occluded` walks an 8-wide BVH (since 6 December; kd-tree packets of each "
        "point's rays before), one ray at a time (16 walks in flight on a tree from 128 MiB); *any-hit"
        " BVH s* and *MB* are its build time and size (built on first use, not part of *build s*). "
        "Embree traces every ray alone (embreex has no packet API).",
        "",
    ]
    return "\n".join(parts)


def write_csv(rows: list[dict[str, Any]], path: Path) -> None:
    keys: list[str] = []
    for r in rows:
        keys += [k for k in r if k not in keys]
    with path.open("w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=keys)
        w.writeheader()
        for r in rows:
            w.writerow({k: (f"{v:.6g}" if isinstance(v, float) else v) for k, v in r.items()})


def plot(rows: list[dict[str, Any]], path: Path, title: str) -> bool:
    plt = pyplot()
    if plt is None:
        return False

    labels = [r["model"] for r in rows]
    x = np.arange(len(rows))
    fig, axes = plt.subplots(2, 1, figsize=(max(8.0, 0.8 * len(rows) + 2), 8), sharex=True)
    light, blue, orange = "#9ecae1", "#2171b5", "#e6550d"
    series = [
        (
            axes[0],
            [
                ("render_1t", "vastray render", light),
                ("batch_1t", "vastray batch", blue),
                ("embree_1t", "Embree", orange),
            ],
            "ratio_batch_1t",
            "primary rays",
        ),
        (
            axes[1],
            [("ao_1t", "vastray occluded", blue), ("eao_1t", "Embree occluded", orange)],
            "ratio_ao_1t",
            "AO rays",
        ),
    ]
    for ax, keys, ratio_key, name in series:
        width = 0.8 / len(keys)
        for i, (key, label, colour) in enumerate(keys):
            vals = [r.get(key, math.nan) for r in rows]
            ax.bar(x + (i - (len(keys) - 1) / 2) * width, vals, width, label=label, color=colour)
        for xi, r in zip(x, rows, strict=True):
            top = max((r.get(k, 0.0) for k, _, _ in keys if math.isfinite(r.get(k, math.nan))), default=0.0)
            if math.isfinite(r.get(ratio_key, math.nan)):
                ax.annotate(f"{r[ratio_key]:.2f}x", (xi, top), ha="center", va="bottom", fontsize=7)
        ax.set_ylabel("Mrays/s, one thread")
        ax.set_title(f"{name}, single thread (labels: vastray / Embree)")
        ax.legend(fontsize=8)
        ax.grid(axis="y", alpha=0.3)
        ax.margins(y=0.12)
    axes[1].set_xticks(x, labels, rotation=35, ha="right")
    save_figure(fig, title, path)
    return True


# ----------------------------------------------------------------------------- main


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument(
        "--models", default="all", help="comma list: mesh stems, plant, mandelbulb, real, procedural, all"
    )
    ap.add_argument("--sizes", default="1e5,1e6,1e7", help="procedural triangle counts (default 1e5,1e6,1e7)")
    ap.add_argument("--width", type=int, default=1024)
    ap.add_argument("--height", type=int, default=768)
    ap.add_argument("--fov", type=float, default=45.0)
    ap.add_argument("--reps", type=int, default=3, help="timed runs per measurement; the best is kept")
    ap.add_argument("--ao-reps", type=int, default=None, help="runs for AO rays (default: --reps)")
    ap.add_argument("--ao-samples", type=int, default=8)
    ap.add_argument(
        "--min-time", type=float, default=3.0, help="repeat cheap measurements until they took this long (s)"
    )
    ap.add_argument("--threads", type=int, default=0, help="'all threads' count (default: hardware threads)")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--no-embree", action="store_true", help="vastray only")
    ap.add_argument(
        "--isa", default=None, help="force the kernels' ISA path (sse2, avx, avx2, avx512): VASTRAY_ISA"
    )
    ap.add_argument("--no-pin", action="store_true", help="import vastray.native in place (no private copy)")
    ap.add_argument("--quick", action="store_true", help="smoke run: two small models, 320x240, 2 runs")
    ap.add_argument("--out", type=Path, default=RESULTS_DIR, help="output folder (default bench/results)")
    ap.add_argument("--name", default=None, help="output file stem (default rays, or rays-quick)")
    args = ap.parse_args(argv)
    if args.quick:
        if args.models == "all":
            args.models = "cow,plant"
        if args.sizes == "1e5,1e6,1e7":
            args.sizes = "1e5"
        args.width, args.height, args.reps, args.min_time = 320, 240, 2, 0.5
    args.ao_reps = args.ao_reps or args.reps
    args.name = args.name or ("rays-quick" if args.quick else "rays")
    return args


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    sizes = [parse_count(s) for s in args.sizes.split(",") if s.strip()]
    specs = select_models([m.strip() for m in args.models.split(",") if m.strip()], sizes)
    nt = args.threads or native.hardware_threads()

    pool: ThreadPoolExecutor | None = None
    if not args.no_embree:
        try:
            import embreex  # noqa: F401

            pool = ThreadPoolExecutor(max_workers=nt)
        except ImportError:
            print("embreex not installed: measuring vastray only (pip install '.[bench]')", file=sys.stderr)

    info = machine_info(
        {
            "vastray native": NATIVE_BUILD,
            "vastray ISA path": f"{isa_path()} (supported here: "
            + (", ".join(native.supported_isas()) if hasattr(native, "supported_isas") else "sse2")
            + ")",
            "vastray hardware threads": str(native.hardware_threads()),
            "all-threads setting": str(nt),
            "embreex": embree_version() or "not installed",
            "models": str(models_dir()),
        }
    )
    print("\n".join(f"{k}: {v}" for k, v in info.items()))
    start = time.perf_counter()
    rows: list[dict[str, Any]] = []
    for spec in specs:
        rows.append(bench_model(spec, args, pool, nt))
        gc.collect()
    if pool is not None:
        pool.shutdown()
    info["total wall time"] = f"{time.perf_counter() - start:.0f} s"

    text = report(rows, info, args, nt)
    print("\n" + text)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / f"{args.name}.md").write_text(text)
    write_csv(rows, args.out / f"{args.name}.csv")
    plotted = False
    if pool is not None or rows:
        title = f"vastray ({isa_path()}) vs Embree, {args.width}x{args.height}, {info['cpu']}"
        plotted = plot(rows, args.out / f"{args.name}.png", title)
    print(f"\nwrote {args.out / args.name}.md, .csv{', .png' if plotted else ''}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
