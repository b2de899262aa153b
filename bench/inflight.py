"""Packets in flight against packets one at a time, on the same in-core tree.

On trees of 128 MiB and more the in-core renderer keeps 8 of a tile's 4x4 packets in
flight and the batch occlusion query 8 of its per-origin AO packets, each stopping where
its next load would likely miss (docs/native-core.md, "Packets in flight").
VASTRAY_INTERLEAVE_BYTES moves that size, and is read at every call, so one process can
trace the same rays through the same tree both ways, alternating within each round so
that a busy machine slows both alike:

* the renderer's primary rays (1024x768, 4x4 packets, shading='normal', its own clock);
* the renderer's AO frame (the same view, shading='ao', 8 samples: a block's AO queries
  go to the backend 16 at a time, occluded_group), its own clock;
* the renderer's sun frame (shading='sun': its primary packets in flight; a block's
  shadow rays are one packet, traced as it is shaded), its own clock;
* AO rays (8 per facing primary hit, 0.2 x the diagonal, as bench/rays.py makes them)
  through `Scene.occluded` (wall time).

One thread. Ratios above 1: packets in flight are faster. Answers must be equal. Writes
inflight.md to bench/results/.

    python bench/inflight.py
    python bench/inflight.py --models plant --sizes 1e6,3e6,1e7
"""

from __future__ import annotations

import argparse
import gc
import os
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from common import RESULTS_DIR, camera_rays, machine_info, markdown_table, parse_count
from kdcost import ao_rays

# (kdcost imports bench/rays.py, which pins one build of the native module.)
from rays import NATIVE_BUILD, isa_path, select_models

from vastray import native
from vastray.camera import frame_bounds
from vastray.renderer import trace

MODES = {"one at a time": str(2**62), "in flight": "0"}


def bench_model(spec: Any, rounds: int) -> dict[str, Any]:
    print(f"\n== {spec.label}", flush=True)
    mesh = spec.load(1)
    vertices = np.ascontiguousarray(mesh.vertices, dtype=np.float64)
    faces = np.ascontiguousarray(mesh.faces, dtype=np.uint32)
    del mesh
    scene = native.Scene(vertices, faces, threads=0)
    lo, hi = (np.asarray(b, dtype=np.float64) for b in scene.bounds)
    cam = frame_bounds(lo, hi, fov=45.0, width=1024, height=768)
    o, d = camera_rays(cam.eye, cam.target, cam.up, cam.fov, cam.width, cam.height)
    ao_o, ao_d, ao_tmax = ao_rays(scene, vertices, faces, o, d, float(np.linalg.norm(hi - lo)))
    best: dict[tuple[str, str], float] = {}
    answers: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    try:
        for _ in range(rounds):
            for mode, size in MODES.items():
                os.environ["VASTRAY_INTERLEAVE_BYTES"] = size
                frame = trace(scene, cam, shading="normal", threads=1)
                ao_frame = trace(scene, cam, shading="ao", ao_samples=8, threads=1)
                sun_frame = trace(scene, cam, shading="sun", threads=1)
                t = time.perf_counter()
                blocked = np.asarray(scene.occluded(ao_o, ao_d, 0, ao_tmax, threads=1), dtype=bool)
                ao_s = time.perf_counter() - t
                best[mode, "render"] = min(best.get((mode, "render"), np.inf), frame.stats.milliseconds / 1e3)
                best[mode, "ao"] = min(best.get((mode, "ao"), np.inf), ao_s)
                for kind, f in (("ao_frame", ao_frame), ("sun_frame", sun_frame)):
                    best[mode, kind] = min(best.get((mode, kind), np.inf), f.stats.milliseconds / 1e3)
                images = (np.asarray(ao_frame.image), np.asarray(sun_frame.image))
                answers[mode] = (np.asarray(frame.prim), blocked, *images)
    finally:
        os.environ.pop("VASTRAY_INTERLEAVE_BYTES", None)
    a, b = answers.values()
    row = {
        "model": spec.label,
        "triangles": len(faces),
        "tree_mib": scene.build_stats["memory_bytes"] / 2**20,
        "default": "in flight" if scene.build_stats["memory_bytes"] >= 128 << 20 else "one at a time",
        "equal": all(np.array_equal(x, y) for x, y in zip(a, b, strict=True)),
    }
    kinds = (("render", len(o)), ("ao", len(ao_o)))
    kinds += (("ao_frame", int(ao_frame.stats.rays)), ("sun_frame", int(sun_frame.stats.rays)))
    for k, n in kinds:
        alone, flight = best["one at a time", k], best["in flight", k]
        row[f"{k}_alone"] = n / alone / 1e6
        row[f"{k}_flight"] = n / flight / 1e6
        row[f"{k}_x"] = alone / flight
    print(
        f"   tree {row['tree_mib']:.0f} MiB | render {row['render_alone']:.2f} -> {row['render_flight']:.2f} "
        f"Mrays/s ({row['render_x']:.2f}x), AO {row['ao_alone']:.2f} -> {row['ao_flight']:.2f} "
        f"({row['ao_x']:.2f}x), AO frame {row['ao_frame_alone']:.2f} -> {row['ao_frame_flight']:.2f} "
        f"({row['ao_frame_x']:.2f}x), sun frame {row['sun_frame_x']:.2f}x, answers equal: {row['equal']}",
        flush=True,
    )
    return row


def report(rows: list[dict[str, Any]], info: dict[str, str]) -> str:
    return "\n".join(
        [
            "# Packets in flight against one at a time (in-core tree)",
            "",
            f"vastray kernels on the **{isa_path()}** path, one thread, the same tree and rays both ways "
            "(VASTRAY_INTERLEAVE_BYTES), alternating within each round, best of the rounds. Ratios above 1: "
            "packets in flight are faster. *default*: what the tree's size gets without the variable "
            "(in flight from 128 MiB). The machine is shared and noisy: read the ratios.",
            "",
            "## Machine",
            "",
            *[f"- {k}: {v}" for k, v in info.items()],
            "",
            "## Rays",
            "",
            markdown_table(
                [
                    "model",
                    "triangles",
                    "tree MiB",
                    "default",
                    "render Mrays/s, one at a time",
                    "in flight",
                    "render x",
                    "AO Mrays/s, one at a time",
                    "in flight",
                    "AO x",
                    "AO frame Mrays/s, one at a time",
                    "in flight",
                    "AO frame x",
                    "sun frame Mrays/s, one at a time",
                    "in flight",
                    "sun frame x",
                    "answers equal",
                ],
                [
                    [
                        r["model"],
                        f"{r['triangles']:,}",
                        f"{r['tree_mib']:.0f}",
                        r["default"],
                        f"{r['render_alone']:.2f}",
                        f"{r['render_flight']:.2f}",
                        f"{r['render_x']:.2f}x",
                        f"{r['ao_alone']:.2f}",
                        f"{r['ao_flight']:.2f}",
                        f"{r['ao_x']:.2f}x",
                        f"{r['ao_frame_alone']:.2f}",
                        f"{r['ao_frame_flight']:.2f}",
                        f"{r['ao_frame_x']:.2f}x",
                        f"{r['sun_frame_alone']:.2f}",
                        f"{r['sun_frame_flight']:.2f}",
                        f"{r['sun_frame_x']:.2f}x",
                        "yes" if r["equal"] else "**no**",
                    ]
                    for r in rows
                ],
            ),
            "",
        ]
    )


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--models", default="stanford-bunny,plant,mandelbulb")
    p.add_argument("--sizes", default="1e6,3e6,1e7", help="procedural triangle counts")
    p.add_argument("--rounds", type=int, default=3)
    p.add_argument("--no-pin", action="store_true", help="use the installed native module as it is")
    p.add_argument("--out", type=Path, default=RESULTS_DIR)
    p.add_argument("--name", default="inflight")
    args = p.parse_args(argv)
    sizes = [parse_count(s) for s in args.sizes.split(",") if s.strip()]
    specs = select_models([m.strip() for m in args.models.split(",") if m.strip()], sizes)
    info = machine_info({"vastray native": NATIVE_BUILD, "vastray ISA path": isa_path()})
    rows = []
    for spec in specs:
        rows.append(bench_model(spec, args.rounds))
        gc.collect()
    text = report(rows, info)
    print("\n" + text)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / f"{args.name}.md").write_text(text)
    print(f"wrote {args.out / args.name}.md")
    return 0 if all(r["equal"] for r in rows) else 1


if __name__ == "__main__":
    raise SystemExit(main())
