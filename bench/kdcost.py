"""The in-core kd-tree's SAH traversal cost against its size, build time and ray speed.

For each model this builds `native.Scene` once per traversal cost (intersection cost
1.5, as the scene's default) and traces the same rays through every tree, one thread,
the trees taken in turn within each round so that a busy machine slows them alike:

* primary rays of a camera framing the model (1024x768): the renderer (4x4 packets,
  shading='normal', its own clock) and the batch `intersect` (single rays, wall time);
* ambient-occlusion rays: 8 cosine-weighted directions about the facing normal of every
  primary hit, 0.2 x the scene diagonal long, through `occluded` (wall time).

Ratios are against the first cost given (above 1: faster than it). Writes kdcost.md
to bench/results/.

    python bench/kdcost.py                                   # 1 and 4, the old and new default
    python bench/kdcost.py --models stanford-bunny,plant --sizes 1e6 --costs 1,2,4,6,8
"""

from __future__ import annotations

import argparse
import gc
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from common import (  # bench/ is a folder of scripts, not a package
    RESULTS_DIR,
    ao_rays_from_hits,
    camera_rays,
    machine_info,
    markdown_table,
    parse_count,
)

# bench/rays.py pins one build of the native module as it is imported (or, with
# --no-pin, takes it as installed); its helpers make the same models and rays.
from rays import NATIVE_BUILD, isa_path, select_models

from vastray import native
from vastray.camera import frame_bounds
from vastray.renderer import trace

AO_SAMPLES = 8


def ao_rays(
    scene: native.Scene,
    vertices: np.ndarray,
    faces: np.ndarray,
    o: np.ndarray,
    d: np.ndarray,
    diagonal: float,
) -> tuple[np.ndarray, np.ndarray, float]:
    """The AO rays of bench/rays.py (seed 1) from this scene's primary hits."""
    hits = scene.intersect(o, d, threads=0)
    return ao_rays_from_hits(vertices, faces, d, hits, AO_SAMPLES, np.random.default_rng(1), diagonal)


def bench_model(spec: Any, costs: list[float], rounds: int) -> list[dict[str, Any]]:
    print(f"\n== {spec.label}", flush=True)
    mesh = spec.load(1)
    vertices = np.ascontiguousarray(mesh.vertices, dtype=np.float64)
    faces = np.ascontiguousarray(mesh.faces, dtype=np.uint32)
    del mesh
    scenes: dict[float, native.Scene] = {}
    rows: dict[float, dict[str, Any]] = {}
    for cost in costs:
        gc.collect()
        t = time.perf_counter()
        scenes[cost] = native.Scene(vertices, faces, threads=0, traversal_cost=cost)
        st = scenes[cost].build_stats
        rows[cost] = {
            "model": spec.label,
            "triangles": len(faces),
            "cost": cost,
            "build_s": time.perf_counter() - t,
            "nodes": st["nodes"],
            "mb": st["memory_bytes"] / 1e6,
            "refs": st["references"] / len(faces),
        }
    first = scenes[costs[0]]
    lo, hi = (np.asarray(b, dtype=np.float64) for b in first.bounds)
    diagonal = float(np.linalg.norm(hi - lo))
    cam = frame_bounds(lo, hi, fov=45.0, width=1024, height=768)
    o, d = camera_rays(cam.eye, cam.target, cam.up, cam.fov, cam.width, cam.height)
    ao_o, ao_d, ao_tmax = ao_rays(first, vertices, faces, o, d, diagonal)
    answers: dict[float, np.ndarray] = {}
    for _ in range(rounds):
        for cost in costs:
            s, row = scenes[cost], rows[cost]
            frame = trace(s, cam, shading="normal", threads=1)
            row["render_s"] = min(row.get("render_s", np.inf), frame.stats.milliseconds / 1e3)
            t = time.perf_counter()
            s.intersect(o, d, threads=1)
            row["batch_s"] = min(row.get("batch_s", np.inf), time.perf_counter() - t)
            t = time.perf_counter()
            answers[cost] = np.asarray(s.occluded(ao_o, ao_d, 0, ao_tmax, threads=1), dtype=bool)
            row["ao_s"] = min(row.get("ao_s", np.inf), time.perf_counter() - t)
    base = rows[costs[0]]
    for cost in costs:
        row = rows[cost]
        row["render_mrays"] = len(o) / row["render_s"] / 1e6
        row["batch_mrays"] = len(o) / row["batch_s"] / 1e6
        row["ao_mrays"] = len(ao_o) / row["ao_s"] / 1e6
        for k in ("render", "batch", "ao"):
            row[f"{k}_x"] = base[f"{k}_s"] / row[f"{k}_s"]
        row["build_x"] = base["build_s"] / row["build_s"]
        # Any tree answers any-hit queries alike up to rays that graze an edge.
        row["ao_agree"] = 100.0 * float(np.mean(answers[cost] == answers[costs[0]]))
        print(
            f"   cost {cost:g}: {row['nodes']:,} nodes, {row['mb']:.1f} MB, build {row['build_s']:.2f} s | "
            f"render {row['render_mrays']:.2f} ({row['render_x']:.2f}x), batch {row['batch_mrays']:.2f} "
            f"({row['batch_x']:.2f}x), AO {row['ao_mrays']:.2f} ({row['ao_x']:.2f}x) Mrays/s",
            flush=True,
        )
    return [rows[c] for c in costs]


def report(rows: list[dict[str, Any]], info: dict[str, str], costs: list[float]) -> str:
    out = [
        "# The in-core kd-tree's SAH traversal cost: size, build and ray speed",
        "",
        f"vastray kernels on the **{isa_path()}** path. Every tree of a model traces the same rays on one "
        f"thread, the trees in turn within each round, best of the rounds. Intersection cost 1.5 throughout. "
        f"Ratios (x) are against traversal cost {costs[0]:g} (above 1: faster or, for build, quicker). "
        "The machine is shared and noisy: read the ratios.",
        "",
        "## Machine",
        "",
        *[f"- {k}: {v}" for k, v in info.items()],
        "",
        "## Trees and rays",
        "",
        markdown_table(
            [
                "model",
                "triangles",
                "traversal cost",
                "kd nodes",
                "kd MB",
                "refs/tri",
                "build s",
                "build x",
                "render Mrays/s",
                "render x",
                "batch Mrays/s",
                "batch x",
                "AO Mrays/s",
                "AO x",
                "AO answers equal %",
            ],
            [
                [
                    r["model"],
                    f"{r['triangles']:,}",
                    f"{r['cost']:g}",
                    f"{r['nodes']:,}",
                    f"{r['mb']:.1f}",
                    f"{r['refs']:.2f}",
                    f"{r['build_s']:.2f}",
                    f"{r['build_x']:.2f}x",
                    f"{r['render_mrays']:.2f}",
                    f"{r['render_x']:.2f}x",
                    f"{r['batch_mrays']:.2f}",
                    f"{r['batch_x']:.2f}x",
                    f"{r['ao_mrays']:.2f}",
                    f"{r['ao_x']:.2f}x",
                    f"{r['ao_agree']:.3f}",
                ]
                for r in rows
            ],
        ),
        "",
        "*render*: the tiled renderer, 4x4 packets, shading='normal', its own clock; *batch*: "
        "`Scene.intersect`, single rays, wall time; *AO*: `Scene.occluded` on 8 rays per primary hit "
        "(one any-hit packet per origin), wall time. *AO answers equal*: rays whose answer matches the "
        "first tree's (trees differ only in where rays that graze an edge land).",
        "",
    ]
    return "\n".join(out)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--models", default="stanford-bunny,plant,mandelbulb")
    p.add_argument("--sizes", default="1e6,1e7", help="procedural triangle counts")
    p.add_argument("--costs", default="1,4", help="SAH traversal costs, the first the reference")
    p.add_argument("--rounds", type=int, default=3)
    p.add_argument("--no-pin", action="store_true", help="use the installed native module as it is")
    p.add_argument("--out", type=Path, default=RESULTS_DIR)
    p.add_argument("--name", default="kdcost")
    args = p.parse_args(argv)
    costs = [float(c) for c in args.costs.split(",")]
    sizes = [parse_count(s) for s in args.sizes.split(",") if s.strip()]
    specs = select_models([m.strip() for m in args.models.split(",") if m.strip()], sizes)
    info = machine_info({"vastray native": NATIVE_BUILD, "vastray ISA path": isa_path()})
    rows: list[dict[str, Any]] = []
    for spec in specs:
        rows += bench_model(spec, costs, args.rounds)
        gc.collect()
    text = report(rows, info, costs)
    print("\n" + text)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / f"{args.name}.md").write_text(text)
    print(f"wrote {args.out / args.name}.md")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
