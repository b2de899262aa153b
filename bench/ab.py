"""Two builds of vastray side by side: the working tree against a git revision, on the
same rays, alternating, for a change to the kernels that should not change an answer.

Each build runs in a child process of its own (two builds of the native module cannot
share one process), started once: it builds every model's scene and makes its rays,
then waits. The parent then asks the two children in turn, round after round, the
order swapped every round, so that a busy machine slows both alike; each child reports
its time and a checksum of its answers, and the run stops if the answers differ (by more
than `--tolerate`, a fraction, when a change may move answers on known boundaries).
The working tree's side is its Python sources with the installed native module: build and
install it first (`make install`); a module older than a native source file stops the
run, as it would measure the code before the change (`--stale` runs it anyway).

Workloads, one thread each (`--threads` for more):

* `batch`: closest hits of the primary rays (1024x768) through `Scene.intersect`;
* `ao`: 8 AO rays per facing primary hit, 0.2 x the diagonal, through `Scene.occluded`
  (as bench/rays.py makes them);
* `shadow`: a ray from each of those hit points along one direction (a distant light),
  through `Scene.occluded`;
* `frame`: the in-core renderer, 1024x768, 4x4 packets, shading='normal', its own clock;
* `sun`: the same frame with shading='sun' (a shadow ray per lit pixel facing the sun);
* `indirect`: the same frame with shading='indirect' (two diffuse rays and a shadow ray
  per pixel);
* `section`: the same frame with shading='headlight' and a section plane through the
  model's centre (keeping x at and above it);
* `ooc`: an out-of-core frame (1280x720, headlight, `--poe`) of each built model given
  with `--ooc`, complete, its own clock; `ooc-sun`: the same with shadow rays;
  `ooc-single`: with single rays (`packets=1`); `ooc-section`: with a section plane
  through the model's centre (which took single rays until packets learnt sections);
  `ooc-ao` and `ooc-indirect`: the AO and indirect shading modes.

Ratios above 1: the working tree is faster. Writes NAME.md to bench/results/.

`--isas A,B` compares two of the kernels' ISA paths (isa.h) of the working tree instead
of two builds: the baseline child runs with VASTRAY_ISA=A, the other with VASTRAY_ISA=B
(a path must be one this CPU runs, `native.supported_isas()`).

`--instructions` counts each workload's instructions instead of timing it: the
children run under valgrind's callgrind with instrumentation off, and switch it on for
the measured call alone (for an out-of-core workload, one more frame of the complete
view, after the timed run's frames). The count does not depend on the machine's load,
so one round settles what timing needs many for, where a change moves the instruction
count; it says nothing of cache misses or of the processor's overlap, which the timed
run measures. Needs valgrind (`apt install valgrind`); runs are 20-50x slower.

`--images` is for a change that is meant to change the out-of-core images at PoE > 0
(a LOD metric, say): the builds' answers may then differ, and the table gives each
build's working set and its image's PSNR and mean absolute error against its own
full-detail (PoE 0) frame of the same view and mode, whose answers must still agree.

    python bench/ab.py --baseline HEAD --models stanford-bunny,plant --sizes 1e6
    python bench/ab.py --baseline HEAD --models plant --sizes 1e7 --ooc plant-1e7.vast
    python bench/ab.py --isas avx2,avx512 --models plant --sizes 1e6 --ooc plant-1e8.vast
    python bench/ab.py --instructions --rounds 1 --reps 1 --models '' --workloads ooc --ooc plant-1e7.vast
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from functools import partial
from pathlib import Path
from typing import Any, TypeVar

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from common import (
    RESULTS_DIR,
    camera_rays,
    format_count,
    geometric_mean,
    machine_info,
    markdown_table,
    models_dir,
    parse_count,
    shadow_rays_from,
)

from build import build_baseline, snapshot_vastray, use_snapshot

# The out-of-core workloads' shading modes.
OOC_SHADING = {
    "ooc": "headlight",
    "ooc-sun": "sun",
    "ooc-single": "headlight",
    "ooc-section": "headlight",
    "ooc-ao": "ao",
    "ooc-indirect": "indirect",
}
OOC_WORKLOADS = tuple(OOC_SHADING)
WORKLOADS = ("batch", "ao", "shadow", "frame", "sun", "indirect", "section", *OOC_WORKLOADS)
PROCEDURAL = ("plant", "mandelbulb")


# ----------------------------------------------------------------------------- child

T = TypeVar("T")

# Where a child under callgrind writes its dumps (set by the parent with --instructions).
CALLGRIND_OUT_ENV = "VASTRAY_AB_CALLGRIND_OUT"


class InstructionCounter:
    """The instructions this process runs in one call. The process runs under callgrind
    with instrumentation off (`--instr-atstart=no`); callgrind_control switches it on,
    zeroes the counters, and dumps them after the call, and waits each time until the
    process has acted on the command, so the dump holds the call and the few Python
    lines around it (its total is its `summary:` line). Without the zeroing, the second
    and later dumps of a process read nonsense (a wrapped negative count, or next to
    nothing) once instrumentation had been off in between."""

    def __init__(self, out_prefix: str) -> None:
        self.out_prefix = out_prefix
        self.dumps = 0

    def _control(self, *args: str) -> None:
        subprocess.run(["callgrind_control", *args, str(os.getpid())], check=True, capture_output=True)

    def count(self, call: Callable[[], T]) -> tuple[T, int]:
        self._control("--instr=on")
        self._control("--zero")
        try:
            result = call()
        finally:
            self._control("--dump=ab")
            self.dumps += 1  # (numbered by callgrind whether or not the call returned)
            self._control("--instr=off")
        dump = Path(f"{self.out_prefix}.{os.getpid()}.{self.dumps}")
        for line in dump.read_text().splitlines():
            if line.startswith("summary:"):
                dump.unlink()
                return result, int(line.split()[1])
        raise RuntimeError(f"{dump}: no summary line (not a callgrind dump?)")


def frame_check(frame: Any) -> int:
    """A checksum of a frame's answers: its triangle ids and its pixels."""
    return int(frame.prim.astype(np.int64).sum()) + int(frame.image.astype(np.int64).sum())


def section_through_centre(bounds: Any) -> list[tuple[float, float, float, float]]:
    """The section workloads' plane: through the model's centre, keeping x at and above it."""
    lo, hi = bounds
    return [(1.0, 0.0, 0.0, -0.5 * (float(lo[0]) + float(hi[0])))]


class Child:
    """A build's side of the run: its scenes, rays and built models, and the workloads."""

    def __init__(self) -> None:
        from vastray import native

        self.native = native
        self.scenes: dict[str, Any] = {}
        self.cache: Any = None
        self.ooc: dict[str, Any] = {}
        self.references: dict[tuple[str, str], np.ndarray] = {}
        out = os.environ.get(CALLGRIND_OUT_ENV)
        self.counter = InstructionCounter(out) if out else None

    def measure(self, call: Callable[[], T]) -> tuple[T, float]:
        """The call's result and its cost: wall-clock seconds, or with --instructions its
        instruction count."""
        if self.counter is not None:
            return self.counter.count(call)
        start = time.perf_counter()
        result = call()
        return result, time.perf_counter() - start

    def load(self, label: str, npz: str) -> dict[str, Any]:
        from common import ao_rays_from_hits

        from vastray.camera import frame_bounds

        data = np.load(npz)
        vertices, faces = data["vertices"], data["faces"]
        scene = self.native.Scene(vertices, faces, threads=0)
        lo, hi = (np.asarray(b, dtype=np.float64) for b in scene.bounds)
        camera = frame_bounds(lo, hi, fov=45.0, width=1024, height=768)
        o, d = camera_rays(camera.eye, camera.target, camera.up, camera.fov, camera.width, camera.height)
        hits = scene.intersect(o, d, threads=0)
        # Input ids are the face indices here: the npz holds what ingest kept.
        ao_o, ao_d, ao_tmax = ao_rays_from_hits(
            vertices, faces, d, hits, 8, np.random.default_rng(1), float(np.linalg.norm(hi - lo))
        )
        self.scenes[label] = (scene, camera, o, d, ao_o, ao_d, ao_tmax)
        return {"rays": len(o), "ao_rays": len(ao_o)}

    def open_model(self, path: str) -> dict[str, Any]:
        from vastray.camera import frame_bounds
        from vastray.outofcore import OutOfCoreModel, make_cache

        if self.cache is None:
            self.cache = make_cache(4 << 30, fetchers=2)
        model = OutOfCoreModel(path, self.cache)
        camera = frame_bounds(*model.bounds, width=1280, height=720)
        self.ooc[path] = (model, camera)
        return {"triangles": int(model.triangle_count)}

    def run(
        self, workload: str, label: str, reps: int, poe: float, images: bool = False, threads: int = 1
    ) -> dict[str, Any]:
        """The workload's cost over `reps` runs, its best time in seconds (with
        --instructions its fewest instructions), and a checksum of its answers."""
        if workload in OOC_WORKLOADS:
            return self.run_ooc(workload, label, reps, poe, images, threads)
        from vastray.renderer import trace

        scene, camera, o, d, ao_o, ao_d, ao_tmax = self.scenes[label]
        call: Callable[[], Any]
        if workload == "batch":
            call = partial(scene.intersect, o, d, threads=threads)
        elif workload == "ao":
            call = partial(scene.occluded, ao_o, ao_d, 0.0, ao_tmax, threads=threads)
        elif workload == "shadow":
            points, towards = shadow_rays_from(ao_o, 8)
            call = partial(scene.occluded, points, towards, threads=threads)
        else:
            params: dict[str, Any] = {"shading": workload if workload in ("sun", "indirect") else "normal"}
            if workload == "section":
                params = {"shading": "headlight", "sections": section_through_centre(scene.bounds)}
            call = partial(trace, scene, camera, threads=threads, **params)
        best, check = float("inf"), 0
        for _ in range(reps):
            answer, cost = self.measure(call)
            if workload == "batch":
                check = int(np.asarray(answer["prim"], dtype=np.int64).sum())
            elif workload in ("ao", "shadow"):
                check = int(np.count_nonzero(answer))
            else:
                if self.counter is None:
                    cost = float(answer.stats.milliseconds) / 1e3  # the renderer's own clock
                check = frame_check(answer)
            best = min(best, cost)
        return {"cost": best, "check": check}

    def run_ooc(
        self, workload: str, label: str, reps: int, poe: float, images: bool, threads: int
    ) -> dict[str, Any]:
        """run() for an out-of-core workload: the time of the frame that completes the view
        or, with --instructions, the instructions of one more frame of the complete view."""
        model, camera = self.ooc[label]
        shading = OOC_SHADING[workload]
        fields: dict[str, Any] = {}
        if workload == "ooc-single":
            fields["packets"] = 1
        elif workload == "ooc-section":
            fields["sections"] = section_through_centre(model.bounds)
        frame_of = partial(
            model.render, camera, pixels_of_error=poe, shading=shading, threads=threads, **fields
        )
        best, check = float("inf"), 0
        extra: dict[str, Any] = {}
        for _ in range(reps):
            frame = model.render_complete(
                camera, pixels_of_error=poe, shading=shading, threads=threads, **fields
            )
            cost = float(frame.stats.milliseconds) / 1e3
            if self.counter is not None:
                frame, cost = self.measure(frame_of)
            check = frame_check(frame)
            if images:
                extra = self.image_error(workload, label, frame, fields)
            best = min(best, cost)
        return {"cost": best, "check": check, **extra}

    def image_error(self, workload: str, label: str, frame: Any, fields: dict[str, Any]) -> dict[str, Any]:
        """The frame's working set, and its error against the full-detail frame of the same
        view and mode (rendered once), with that frame's checksum."""
        from tradeoff import psnr  # (it imports vastray: here the child's snapshot is in place)

        model, camera = self.ooc[label]
        key = (workload, label)
        if key not in self.references:
            full = model.render_complete(
                camera, pixels_of_error=0.0, shading=OOC_SHADING[workload], threads=0, **fields
            )
            self.references[key] = full.image.astype(np.float64)
        reference = self.references[key]
        return {
            "working_set_mib": float(frame.stats.working_set_bytes) / 2**20,
            "psnr": psnr(frame.image, reference),
            "mae": float(np.mean(np.abs(frame.image.astype(np.float64) - reference))),
            "reference_check": int(reference.sum()),
        }


def child_main(snapshot: str) -> int:
    use_snapshot(snapshot)
    from vastray import native

    child = Child()
    print(json.dumps({"isa": native.isa()}), flush=True)
    for line in sys.stdin:
        request = json.loads(line)
        op = request.pop("op")
        reply = getattr(child, op)(**request)
        print(json.dumps(reply), flush=True)
    return 0


# ----------------------------------------------------------------------------- parent


class Build:
    """A child process with one build's vastray. With `callgrind_out` (a path prefix) it
    runs under callgrind, uninstrumented but for the calls it counts (InstructionCounter);
    valgrind's own messages go to the prefix's .log."""

    def __init__(
        self,
        name: str,
        snapshot: Path,
        description: str,
        isa: str | None = None,
        callgrind_out: str | None = None,
    ) -> None:
        self.name, self.description = name, description
        here = str(Path(__file__).resolve())
        env = dict(os.environ)
        if isa is not None:
            env["VASTRAY_ISA"] = isa
        command = [sys.executable, here, "--child", str(snapshot)]
        if callgrind_out is not None:
            env[CALLGRIND_OUT_ENV] = callgrind_out
            command = [
                "valgrind",
                "--tool=callgrind",
                "--instr-atstart=no",
                f"--callgrind-out-file={callgrind_out}.%p",
                f"--log-file={callgrind_out}.log",
                *command,
            ]
        self.proc = subprocess.Popen(
            command,
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            text=True,
            env=env,
        )
        self.isa = self._read()["isa"]

    def _read(self) -> dict[str, Any]:
        assert self.proc.stdout is not None
        line = self.proc.stdout.readline()
        if not line:
            raise SystemExit(f"the {self.name} child died (exit {self.proc.wait()})")
        return json.loads(line)

    def ask(self, op: str, **args: Any) -> dict[str, Any]:
        assert self.proc.stdin is not None
        self.proc.stdin.write(json.dumps({"op": op, **args}) + "\n")
        self.proc.stdin.flush()
        return self._read()

    def close(self) -> None:
        if self.proc.stdin:
            self.proc.stdin.close()
        self.proc.wait()


def model_meshes(names: list[str], sizes: list[int], folder: Path) -> list[tuple[str, Path]]:
    """Each model's vertices and faces, made once by the working tree's vastray, in an npz
    that both builds read (so both trace the same triangles)."""
    from vastray.ingest import load_mesh
    from vastray.scenes import to_mesh

    out = []
    for name in names:
        if name in PROCEDURAL:
            made = [(f"{name}-{format_count(n)}", lambda n=n, g=name: to_mesh(g, n, 1)) for n in sizes]
        else:
            matches = sorted(p for p in models_dir().glob(f"{name}.*"))
            if not matches:
                raise SystemExit(f"no mesh {name!r} in {models_dir()}")
            made = [(name, lambda p=matches[0]: load_mesh(p))]
        for label, make in made:
            mesh = make()
            path = folder / f"{label}.npz"
            np.savez(
                path,
                vertices=np.ascontiguousarray(mesh.vertices, dtype=np.float64),
                faces=np.ascontiguousarray(mesh.faces, dtype=np.uint32),
            )
            out.append((label, path))
            print(f"{label}: {len(mesh.faces):,} triangles", flush=True)
    return out


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    workloads = [w for w in args.workloads.split(",") if w]
    unknown = set(workloads) - set(WORKLOADS)
    if unknown:
        raise SystemExit(f"unknown workloads {sorted(unknown)} (known: {', '.join(WORKLOADS)})")
    sizes = [parse_count(s) for s in args.sizes.split(",") if s]
    names = [m for m in args.models.split(",") if m]
    ooc = [str(Path(p).resolve()) for p in args.ooc]
    isas = [i for i in (args.isas or "").split(",") if i]
    if args.instructions and shutil.which("callgrind_control") is None:
        raise SystemExit("--instructions needs valgrind's callgrind (apt install valgrind)")
    if args.isas is not None and len(isas) != 2:
        raise SystemExit(f"--isas takes two paths, baseline first (got {args.isas!r})")
    with tempfile.TemporaryDirectory(prefix="vastray-ab-") as tmp:
        now_pkg, now_desc = snapshot_vastray(require_fresh=not args.stale)
        meshes = model_meshes(names, sizes, Path(tmp))

        def out(name: str) -> str | None:
            return str(Path(tmp) / f"callgrind-{name}") if args.instructions else None

        if isas:
            builds = [
                Build("now", now_pkg, now_desc, isas[1], out("now")),
                Build("baseline", now_pkg, now_desc, isas[0], out("baseline")),
            ]
        else:
            base_pkg, base_desc = build_baseline(args.baseline)
            builds = [
                Build("now", now_pkg, now_desc, callgrind_out=out("now")),
                Build("baseline", base_pkg, base_desc, callgrind_out=out("baseline")),
            ]
        try:
            for b in builds:  # one after the other: their scene builds would compete
                for label, path in meshes:
                    b.ask("load", label=label, npz=str(path))
                for path in ooc:
                    b.ask("open_model", path=path)
            jobs = [(w, label) for w in workloads if w not in OOC_WORKLOADS for label, _ in meshes]
            jobs += [(w, path) for w in workloads if w in OOC_WORKLOADS for path in ooc]
            best: dict[tuple[str, str, str], float] = {}
            quality: dict[tuple[str, str, str], dict[str, Any]] = {}
            differences: dict[tuple[str, str], dict[str, int]] = {}
            for r in range(args.rounds):
                order = builds if r % 2 == 0 else builds[::-1]
                for workload, label in jobs:
                    images = args.images and workload in OOC_WORKLOADS
                    checks = {}
                    for b in order:
                        reply = b.ask(
                            "run",
                            workload=workload,
                            label=label,
                            reps=args.reps,
                            poe=args.poe,
                            images=images,
                            threads=args.threads,
                        )
                        key = (workload, label, b.name)
                        best[key] = min(best.get(key, float("inf")), reply["cost"])
                        checks[b.name] = reply["reference_check" if images else "check"]
                        if images:
                            quality[key] = reply
                    if len(set(checks.values())) != 1:
                        what = "full-detail answers" if images else "answers"
                        values = list(checks.values())
                        spread = max(values) - min(values)
                        if spread > args.tolerate * max(abs(v) for v in values):
                            raise SystemExit(f"{workload} {label}: the builds' {what} differ ({checks})")
                        differences[(workload, label)] = checks
                print(f"round {r + 1}/{args.rounds} done", flush=True)
        finally:
            for b in builds:
                b.close()
    rows, ratios = [], []
    unit, scale = ("M instructions", 1e-6) if args.instructions else ("ms", 1e3)
    header = ["workload", "model", f"baseline {unit}", f"now {unit}", "baseline / now"]
    if quality:
        header += ["working set MiB (baseline, now)", "PSNR dB (baseline, now)", "MAE (baseline, now)"]
    for workload, label in jobs:
        now, base = best[(workload, label, "now")], best[(workload, label, "baseline")]
        ratios.append(base / now)
        name = Path(label).name if workload in OOC_WORKLOADS else label
        row = [workload, name, f"{base * scale:.1f}", f"{now * scale:.1f}", f"{base / now:.3f}x"]
        if quality:
            pair = [quality.get((workload, label, side)) for side in ("baseline", "now")]
            columns = (("working_set_mib", ".0f"), ("psnr", ".2f"), ("mae", ".2f"))
            row += [", ".join(f"{q[k]:{fmt}}" for q in pair if q) for k, fmt in columns]
        rows.append(row)
    if isas:
        info = machine_info(
            {"build (both)": now_desc, "ISA path": f"baseline {builds[1].isa}, now {builds[0].isa}"}
        )
    else:
        info = machine_info({"now": now_desc, "baseline": base_desc, "ISA path (both)": builds[0].isa})
    lines = [
        "# Two ISA paths side by side" if isas else "# Two builds side by side",
        "",
        f"`{' '.join(['python', 'bench/ab.py', *sys.argv[1:]])}`",
        "",
        *(f"- {k}: {v}" for k, v in info.items()),
        "",
        ("Instructions counted by callgrind (the fewest of " if args.instructions else "Best of ")
        + f"{args.rounds} rounds x {args.reps} runs per build"
        + ("), " if args.instructions else ", alternating; ")
        + ("one thread; " if args.threads == 1 else f"{args.threads} threads; ")
        + (
            "images may differ (--images): PSNR and MAE (0-255) are each build's against its own "
            "full-detail frame, and those were equal."
            if args.images
            else "the answers of both builds were equal in every run."
            if not differences
            else "the answers' checksums differed within --tolerate "
            + f"{args.tolerate:g}: "
            + "; ".join(f"{w} {Path(lb).name} {c}" for (w, lb), c in differences.items())
            + "."
        ),
        "",
        markdown_table(header, rows),
        "",
        f"Geometric mean: {geometric_mean(ratios):.3f}x",
    ]
    text = "\n".join(lines) + "\n"
    print(text)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / f"{args.name}.md").write_text(text)
    return 0


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--baseline", default="HEAD", help="git revision to compare with (default HEAD)")
    ap.add_argument(
        "--isas",
        default=None,
        help="compare two ISA paths of the working tree instead (baseline first, e.g. avx2,avx512)",
    )
    ap.add_argument("--models", default="stanford-bunny,plant", help="mesh stems, plant, mandelbulb")
    ap.add_argument("--sizes", default="1e6", help="procedural triangle counts (default 1e6)")
    ap.add_argument("--workloads", default="batch,ao,frame,ooc", help=f"of {', '.join(WORKLOADS)}")
    ap.add_argument("--ooc", action="append", default=[], help="a built model (.vast) for 'ooc' (repeatable)")
    ap.add_argument("--poe", type=float, default=2.0, help="pixels of error of the out-of-core frames")
    ap.add_argument(
        "--images",
        action="store_true",
        help="the out-of-core images may differ: report each build's error against full detail",
    )
    ap.add_argument(
        "--tolerate",
        type=float,
        default=0.0,
        help="the builds' answer checksums (e.g. occluded-ray counts) may differ by this fraction; "
        "the report lists each difference (default 0: any difference stops the run)",
    )
    ap.add_argument(
        "--instructions",
        action="store_true",
        help="count instructions under callgrind instead of timing (needs valgrind; one round is enough)",
    )
    ap.add_argument("--threads", type=int, default=1, help="threads of every workload (default 1)")
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--reps", type=int, default=2, help="runs per build per round (the best is kept)")
    ap.add_argument("--out", type=Path, default=RESULTS_DIR)
    ap.add_argument("--name", default="ab")
    ap.add_argument(
        "--stale",
        action="store_true",
        help="measure the installed native module even where native sources changed after it was built "
        "(by default the run stops: it would not measure the working tree)",
    )
    return ap.parse_args(argv)


if __name__ == "__main__":
    if len(sys.argv) == 3 and sys.argv[1] == "--child":
        sys.exit(child_main(sys.argv[2]))
    sys.exit(main())
