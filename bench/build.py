"""Throughput, memory and file size of the out-of-core model builder (`vastray build`).

Not a test. For every real mesh in ../shared/models ($VASTRAY_MODELS) and for the
procedural `plant` and `mandelbulb` scenes at 10^6 and 10^7 triangles (`--sizes`, add
1e8 for the big one) this measures, one build per fresh subprocess:

* the build at the default budget (`--memory`, 2G) on all hardware threads: end-to-end
  seconds and triangles/s, the builder's own phase times (read, split, build, write) and
  the native writer's kd-tree build and emit times, peak RSS, file size, bytes per
  triangle, LZ4 compression ratio, triangle references per triangle, voxel kinds;
* the same build on one thread, run right beside it (thread scaling as a ratio measured
  side by side, the only speed figure worth reading on a shared, noisy machine);
* a forced out-of-core build with a small budget (a third of the triangle soup, 36 B per
  triangle, at least the builder's minimum), which exercises the out-of-core split path.

Procedural inputs are generated once with `vastray scene` into a cache folder
(bench/.cache) as binary PLY and reused, so build times measure the builder reading a
file, not the generator; generation time is reported on its own. Before each build the
input file's pages are dropped from the OS page cache (posix_fadvise DONTNEED), so the
first read comes from disk. Writes build.md, build.csv and build.png to bench/results/.

    python bench/build.py                         # real meshes + 1e6, 1e7 (about 10 minutes)
    python bench/build.py --sizes 1e6,1e7,1e8     # adds 10^8 (long; 2.3 GB input, ~10 GB scratch)
    python bench/build.py --models plant --sizes 1e6 --no-ooc
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import os
import re
import resource
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))

from common import (  # bench/ is a folder of scripts, not a package
    REPO_ROOT,
    RESULTS_DIR,
    command_and_machine,
    fmt,
    format_count,
    git_revision,
    machine_info,
    markdown_table,
    models_dir,
    parse_count,
    pyplot,
    save_figure,
)

BENCH_DIR = Path(__file__).resolve().parent
DEFAULT_CACHE = BENCH_DIR / ".cache"
PROCEDURAL = ("plant", "mandelbulb")
MESH_SUFFIXES = (".obj", ".ply", ".stl", ".off", ".glb", ".gltf")
SOUP_BYTES_PER_TRIANGLE = 36  # 9 float32 corners
MiB = 1 << 20
GiB = 1 << 30
CHILD_FLAG = "--child"
CLI_FLAG = "--cli"
OBJ_FLAG = "--write-obj"
REPORT_TAG = "@@vastray-build-report@@ "

# Paper 000 (Afra 2012), Table 6: construction statistics, single-threaded build on an
# Intel Core i7-2600. Size in decimal GB; "compr." is the compressed size as a share of
# the full uncompressed structure (kd-tree, voxels, triangles).
PAPER_TABLE6 = (
    # model, triangles, size bytes, compressed/uncompressed, build seconds, (as printed)
    ("Asian Dragon", 7e6, 0.4e9, 0.70, 5 * 60, "7M", "0.4 GB", "70%", "5m"),
    ("Power Plant", 12e6, 0.5e9, 0.54, 7 * 60, "12M", "0.5 GB", "54%", "7m"),
    ("Lucy", 28e6, 1.5e9, 0.68, 21 * 60, "28M", "1.5 GB", "68%", "21m"),
    ("MPI v1.0", 73e6, 4.6e9, 0.58, 63 * 60, "73M", "4.6 GB", "58%", "1h 3m"),
    ("Boeing 777", 337e6, 31.4e9, 0.66, 7 * 3600 + 43 * 60, "337M", "31.4 GB", "66%", "7h 43m"),
    ("Mandelbulb", 354e6, 7.5e9, 0.59, 3600 + 44 * 60, "354M", "7.5 GB", "59%", "1h 44m"),
)
# Our nearest analogue of each paper model (by kind of geometry), for the comparison.
ANALOGUES = {
    "mandelbulb": "Mandelbulb",
    "plant": "Power Plant",
    "stanford-bunny": "Lucy",
    "nefertiti": "Lucy",
}
TARGET_RATE = 1_000_000  # triangles/s end to end on 2 cores
TARGET_BIG = 100_000_000  # triangles ...
TARGET_BIG_BUDGET = 2 * GiB  # ... within this budget
TARGET_BIG_SECONDS = 100  # ... and this time


# ----------------------------------------------------------------------------- child process


def snapshot_vastray(require_fresh: bool = False) -> tuple[Path, str]:
    """Copies the vastray package (Python sources and the built native module) into a
    private folder and returns (folder, description).

    Others edit and rebuild the package while a long benchmark runs; every build of one
    run must use the same code, Python and native alike (pinning only the native module
    is not enough: new Python next to an old native module fails).
    With `require_fresh`, a module older than a native source file is refused: a run that
    compares the working tree with something else would measure the old build.
    """
    import atexit

    # Where the editable install keeps the native module, asked of a separate interpreter
    # so that this one has not imported vastray yet.
    # Run elsewhere: `-c` puts the working directory first on the path, and from the
    # repository root that is the source tree, whose `vastray/` has no native module
    # unless the install is editable.
    probe = "import importlib.util as u; s = u.find_spec('vastray.native'); print(s.origin if s else '')"
    found = subprocess.run(
        [sys.executable, "-c", probe], capture_output=True, text=True, check=True, cwd=tempfile.gettempdir()
    )
    if not found.stdout.strip():
        raise SystemExit("bench/build.py: vastray's native module is not installed (make install)")
    so = Path(found.stdout.strip())
    folder = Path(tempfile.mkdtemp(prefix="vastray-bench-"))
    atexit.register(shutil.rmtree, folder, ignore_errors=True)
    ignore = shutil.ignore_patterns("__pycache__", "*.so", "*.pyd")
    shutil.copytree(REPO_ROOT / "vastray", folder / "vastray", ignore=ignore)
    shutil.copy2(so, folder / "vastray" / so.name)
    built = so.stat().st_mtime
    stamp = time.strftime("%Y-%m-%dT%H:%M:%S%z", time.localtime(built))
    sources = [p for p in (REPO_ROOT / "native").rglob("*") if p.is_file()]
    stale = [p for p in sources if p.stat().st_mtime > built]
    desc = f"{so} ({so.stat().st_size:,} bytes, built {stamp}) and vastray/*.py, copied at start"
    if stale and require_fresh:
        raise SystemExit(
            f"{len(stale)} native source file(s) ({stale[0].relative_to(REPO_ROOT)} among them) changed "
            f"after the installed module was built ({so}, {stamp}): rebuild it (make install) so that the "
            "run measures the working tree, or pass --stale to measure the module as it is"
        )
    if stale:
        desc += f"; WARNING: {len(stale)} native source file(s) are newer than the module"
    return folder, desc


def use_snapshot(folder: str) -> None:
    """Makes `import vastray` load the snapshot rather than the editable install."""
    if "vastray" in sys.modules:
        raise RuntimeError("use_snapshot() must run before vastray is imported")
    # The editable install puts a finder in front of sys.meta_path that maps vastray to
    # the working tree whatever sys.path says; drop it and put the snapshot first.
    sys.meta_path[:] = [f for f in sys.meta_path if not type(f).__module__.startswith("_editable_")]
    sys.path.insert(0, folder)


def build_baseline(rev: str) -> tuple[Path, str]:
    """The vastray package of git revision `rev`, Python sources and a native module built
    from that revision (Release, baseline flags), in a private folder: builds of the
    current code and of `rev` then alternate in one run (the before/after table)."""
    import atexit

    folder = Path(tempfile.mkdtemp(prefix="vastray-baseline-"))
    atexit.register(shutil.rmtree, folder, ignore_errors=True)
    src = folder / "src"
    src.mkdir()
    commit = subprocess.run(
        ["git", "rev-parse", "--short", rev], cwd=REPO_ROOT, capture_output=True, text=True, check=True
    ).stdout.strip()
    archive = subprocess.run(
        ["git", "archive", commit], cwd=REPO_ROOT, capture_output=True, check=True
    ).stdout
    subprocess.run(["tar", "-x", "-C", str(src)], input=archive, check=True)
    import pybind11

    bin_dir = Path(sys.executable).parent
    build = folder / "build"
    print(f"baseline {rev} ({commit}): building its native module", file=sys.stderr, flush=True)
    cmake = str(bin_dir / "cmake")
    configure = [
        cmake,
        "-S",
        str(src),
        "-B",
        str(build),
        "-G",
        "Ninja",
        f"-DCMAKE_MAKE_PROGRAM={bin_dir / 'ninja'}",
    ]
    configure += ["-DCMAKE_BUILD_TYPE=Release", f"-Dpybind11_DIR={pybind11.get_cmake_dir()}"]
    configure += [f"-DPython_EXECUTABLE={sys.executable}"]
    subprocess.run(configure, check=True, stdout=subprocess.DEVNULL)
    subprocess.run(
        [cmake, "--build", str(build), "--target", "native"], check=True, stdout=subprocess.DEVNULL
    )
    so = next((build / "native").glob("native*.so"))
    package = folder / "pkg"
    shutil.copytree(src / "vastray", package / "vastray", ignore=shutil.ignore_patterns("__pycache__"))
    shutil.copy2(so, package / "vastray" / so.name)
    return package, f"{rev} ({commit}), built for this run"


def _jsonable(value: Any) -> Any:
    if hasattr(value, "item"):
        return value.item()
    if hasattr(value, "tolist"):
        return value.tolist()
    return str(value)


class MemorySampler:
    """Samples this process's resident memory split by kind (/proc/self/status: RssAnon =
    heap and other private memory, RssFile = pages of mapped files) every `interval`
    seconds on a thread, keeping the peak of each per build phase.

    The kernel's high-water mark (ru_maxrss) counts both kinds together; pages of a
    memory-mapped input or scratch file are clean and the kernel drops them under memory
    pressure, so the anonymous peak is what a budget has to hold. A sampled peak can miss
    a spike shorter than the interval.
    """

    def __init__(self, interval: float = 0.02) -> None:
        self.interval = interval
        self.phase = "open"  # before the first progress event: opening the input
        self.peaks: dict[str, dict[str, int]] = {}
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    @staticmethod
    def read() -> dict[str, int]:
        out: dict[str, int] = {}
        try:
            for line in Path("/proc/self/status").read_text().splitlines():
                key, _, rest = line.partition(":")
                if key in ("RssAnon", "RssFile", "RssShmem"):
                    out[key] = int(rest.split()[0]) * 1024
        except (OSError, ValueError, IndexError):
            pass
        return out

    def _run(self) -> None:
        while not self._stop.wait(self.interval):
            self.sample()

    def sample(self) -> None:
        now = self.read()
        peak = self.peaks.setdefault(self.phase, {})
        for key, value in now.items():
            peak[key] = max(peak.get(key, 0), value)

    def __enter__(self) -> MemorySampler:
        self.sample()
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join()
        self.sample()


def _cpu(who: int) -> float:
    usage = resource.getrusage(who)
    return usage.ru_utime + usage.ru_stime


def child_main(spec_text: str) -> int:
    """One build in this (fresh) process; prints the builder's report as one JSON line."""
    spec = json.loads(spec_text)
    use_snapshot(spec["snapshot"])
    from vastray.build import BuildOptions, build_model

    if spec.get("baseline"):
        # The RSS of a child that has imported what a build imports, and built nothing:
        # every input streams through vastray.triangle_readers.
        import vastray.native
        from vastray.triangle_readers import open_triangles  # noqa: F401

        peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
        where = {"build": sys.modules["vastray.build"].__file__, "native": vastray.native.__file__}
        anon = MemorySampler.read().get("RssAnon", 0)
        print(REPORT_TAG + json.dumps({"peak_rss_bytes": peak, "anon_bytes": anon, **where}), flush=True)
        return 0

    label = spec["label"]
    state = {"phase": "", "printed": time.perf_counter()}

    sampler = MemorySampler()

    def progress(p: Any) -> None:
        sampler.phase = p.phase
        now = time.perf_counter()
        if p.phase != state["phase"] or now - state["printed"] > 15.0:
            done = f" {p.done / max(1, p.total):.0%}" if p.phase == state["phase"] else ""
            state["phase"], state["printed"] = p.phase, now
            print(f"      {label}: {p.phase}{done} at {p.elapsed:.1f} s", file=sys.stderr, flush=True)

    options = BuildOptions(
        memory=int(spec["memory"]),
        threads=int(spec["threads"]),
        overwrite=True,
        compact_triangles=bool(spec.get("compact_triangles", False)),
    )
    # CPU of this (main) thread against the whole process's: the main thread runs all the
    # Python (reading, splitting) and its share of the native work, so
    # total / main bounds the speedup more threads could give, however busy the machine.
    main0, all0 = _cpu(resource.RUSAGE_THREAD), _cpu(resource.RUSAGE_SELF)
    with sampler:
        report = build_model(spec["input"], spec["output"], options, progress=progress)
    report["cpu_main_thread_s"] = _cpu(resource.RUSAGE_THREAD) - main0
    report["cpu_all_threads_s"] = _cpu(resource.RUSAGE_SELF) - all0
    report["sampled_rss_peaks"] = sampler.peaks
    print(REPORT_TAG + json.dumps(report, default=_jsonable), flush=True)
    return 0


class BuildFailedError(RuntimeError):
    pass


def run_child(spec: dict[str, Any]) -> tuple[dict[str, Any], dict[str, Any]]:
    """Runs one build in a fresh interpreter. Returns (the builder's report, what the
    parent saw: process wall time and the child's rusage from wait4)."""
    cmd = [sys.executable, str(Path(__file__).resolve()), CHILD_FLAG, json.dumps(spec)]
    tail: list[str] = []

    start = time.perf_counter()
    proc = subprocess.Popen(
        cmd, cwd=REPO_ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, bufsize=1
    )
    assert proc.stdout is not None and proc.stderr is not None

    def relay(stream: Any) -> None:
        for line in stream:
            sys.stderr.write(line)
            sys.stderr.flush()
            tail.append(line)
            del tail[:-30]

    relay_thread = threading.Thread(target=relay, args=(proc.stderr,), daemon=True)
    relay_thread.start()
    out = proc.stdout.read()
    # wait4 gives this child's own rusage (RUSAGE_CHILDREN is a max over all children).
    _, status, usage = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - start
    proc.returncode = os.waitstatus_to_exitcode(status)
    relay_thread.join()
    proc.stdout.close()
    proc.stderr.close()
    children = resource.getrusage(resource.RUSAGE_CHILDREN)
    lines = [ln for ln in out.splitlines() if ln.startswith(REPORT_TAG)]
    if proc.returncode != 0 or not lines:
        raise BuildFailedError(f"exit status {proc.returncode}: " + "".join(tail[-8:]).strip())
    seen = {
        "process_s": wall,
        "wait4_maxrss_bytes": usage.ru_maxrss * 1024,
        "children_maxrss_bytes": children.ru_maxrss * 1024,
        "cpu_user_s": usage.ru_utime,
        "cpu_sys_s": usage.ru_stime,
        "disk_read_bytes": usage.ru_inblock * 512,
        "disk_write_bytes": usage.ru_oublock * 512,
        "major_faults": usage.ru_majflt,
    }
    return json.loads(lines[-1][len(REPORT_TAG) :]), seen


# ----------------------------------------------------------------------------- inputs


@dataclass
class Model:
    label: str
    family: str  # 'real', 'plant', 'mandelbulb'
    path: Path
    triangles: int  # in the input file (procedural: what the generator made)
    requested: int = 0  # procedural: the size asked for
    gen_seconds: float = math.nan
    cached: bool = False


def ply_face_count(path: Path) -> int:
    with open(path, "rb") as f:
        head = f.read(4096).split(b"end_header", 1)[0].decode("ascii", "replace")
    match = re.search(r"element face (\d+)", head)
    return int(match.group(1)) if match else 0


def obj_face_count(path: Path) -> int:
    count = 0
    with open(path, "rb") as f:
        for line in f:
            if line.startswith(b"f "):
                count += len(line.split()) - 3  # a polygon fans into n - 2 triangles
    return count


def real_models(names: list[str]) -> list[Model]:
    folder = models_dir()
    if not folder.is_dir():
        print(f"warning: no models folder at {folder} (set VASTRAY_MODELS)", file=sys.stderr)
        return []
    files = sorted(p for p in folder.iterdir() if p.suffix.lower() in MESH_SUFFIXES)
    chosen: list[Path] = []
    for name in names:
        if name in ("all", "real"):
            chosen += files
        elif name not in ("procedural", *PROCEDURAL):
            matches = [p for p in files if p.stem == name] or [p for p in files if p.stem.startswith(name)]
            if len(matches) != 1:
                known = ", ".join([p.stem for p in files] + list(PROCEDURAL))
                raise SystemExit(f"unknown or ambiguous model {name!r} (known: {known})")
            chosen += matches
    out: list[Model] = []
    for p in dict.fromkeys(chosen):
        tris = obj_face_count(p) if p.suffix.lower() == ".obj" else 0
        out.append(Model(p.stem, "real", p, tris))
    return sorted(out, key=lambda m: (m.triangles, m.label))


def procedural_generators(names: list[str]) -> list[str]:
    gens: list[str] = []
    for name in names:
        if name in ("all", "procedural"):
            gens += PROCEDURAL
        elif name in PROCEDURAL:
            gens.append(name)
    return list(dict.fromkeys(gens))


def ensure_obj(model: Model, snapshot: str) -> Model:
    """The procedural model as a Wavefront OBJ in the cache (its PLY's vertices and faces
    as text, without colours, an `o` part per million faces), written when missing."""
    path = model.path.with_suffix(".obj")
    label = model.label + "-obj"
    done_mark = path.with_suffix(".obj.done")
    if path.is_file() and done_mark.is_file():
        print(f"  {label}: cached {path}", file=sys.stderr, flush=True)
        return Model(label, model.family, path, model.triangles, model.requested, math.nan, True)
    print(f"  {label}: writing {path} from {model.path.name}", file=sys.stderr, flush=True)
    script = str(Path(__file__).resolve())
    cmd = [sys.executable, script, OBJ_FLAG, snapshot, str(model.path), str(path)]
    start = time.perf_counter()
    subprocess.run(cmd, cwd=REPO_ROOT, check=True)
    seconds = time.perf_counter() - start
    done_mark.write_text(f"{seconds:.1f}\n")
    return Model(label, model.family, path, model.triangles, model.requested, seconds, False)


def write_obj(ply: Path, obj: Path) -> None:
    """Streams a PLY into an OBJ: Python's % formatting of a whole block of numbers at a
    time writes about 10^7 numbers a second."""
    import numpy as np

    from vastray.triangle_readers import open_triangles

    source = open_triangles(ply)
    table = source.vertices
    assert table is not None
    partial = obj.with_name(obj.name + ".partial")
    block = 1 << 20
    with open(partial, "w") as f:
        f.write(f"# {ply.name} as OBJ (vastray bench/build.py)\n")
        buffer = table.buffer()
        for start in range(0, table.count, block):
            xyz = table.xyz(buffer, start, min(table.count, start + block)).astype(np.float32)
            f.write(("v %.9g %.9g %.9g\n" * len(xyz)) % tuple(xyz.ravel().tolist()))
        for k, chunk in enumerate(source.chunks(block)):
            f.write(f"o part{k}\n")
            faces = np.asarray(chunk.indices, dtype=np.int64) + 1
            f.write(("f %d %d %d\n" * len(faces)) % tuple(faces.ravel().tolist()))
    partial.replace(obj)


def ensure_generated(name: str, size: int, seed: int, cache: Path, snapshot: str) -> Model:
    """The scene as a binary PLY in the cache, generated by `vastray scene` when missing."""
    label = f"{name}-{format_count(size)}"
    path = cache / f"{label}-s{seed}.ply"
    meta_path = path.with_suffix(".json")
    if path.is_file():
        meta: dict[str, Any] = {}
        if meta_path.is_file():
            meta = json.loads(meta_path.read_text())
        if meta.get("file_bytes") == path.stat().st_size:
            print(f"  {label}: cached {path}", file=sys.stderr, flush=True)
            return Model(label, name, path, int(meta["triangles"]), size, float(meta["seconds"]), True)
        print(f"  {label}: cached {path} (no generation record)", file=sys.stderr, flush=True)
        return Model(label, name, path, ply_face_count(path), size, math.nan, True)
    cache.mkdir(parents=True, exist_ok=True)
    # `vastray scene`, run from the snapshot (bench/build.py --cli SNAPSHOT ARGS...).
    cli = ["scene", name, "--triangles", str(size), "--seed", str(seed), "-o", str(path)]
    cmd = [sys.executable, str(Path(__file__).resolve()), CLI_FLAG, snapshot, *cli]
    print(f"  {label}: generating (vastray {' '.join(cli)})", file=sys.stderr, flush=True)
    start = time.perf_counter()
    done = subprocess.run(cmd, cwd=REPO_ROOT, stdout=subprocess.PIPE, text=True)
    seconds = time.perf_counter() - start
    if done.returncode != 0 or not path.is_file():
        raise SystemExit(f"generating {label} failed (exit status {done.returncode})")
    triangles = ply_face_count(path)
    meta = {
        "scene": name,
        "requested": size,
        "seed": seed,
        "triangles": triangles,
        "file_bytes": path.stat().st_size,
        "seconds": seconds,
        "git": git_revision(),
        "date": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
    }
    meta_path.write_text(json.dumps(meta, indent=1) + "\n")
    print(f"  {label}: {triangles:,} triangles in {seconds:.1f} s", file=sys.stderr, flush=True)
    return Model(label, name, path, triangles, size, seconds, False)


# ----------------------------------------------------------------------------- builds


def shown_path(path: Path) -> str:
    """A path relative to the repository when it lies inside it."""
    try:
        return str(path.resolve().relative_to(REPO_ROOT))
    except ValueError:
        return str(path)


def budget_text(nbytes: int) -> str:
    if nbytes % GiB == 0:
        return f"{nbytes // GiB}G"
    return f"{nbytes / MiB:.0f}M"


# --compact-triangles: every build of the run writes compact triangle blocks (set by main).
COMPACT_TRIANGLES = [False]


def ooc_budget(triangles: int, fraction: float, min_budget: int) -> int:
    """A budget of `fraction` of the triangle soup, rounded up to a MiB, at least the minimum."""
    want = max(min_budget, int(triangles * SOUP_BYTES_PER_TRIANGLE * fraction))
    return -(-want // MiB) * MiB


def one_build(
    model: Model, kind: str, memory: int, threads: int, snapshot: str, workdir: Path
) -> dict[str, Any]:
    """Drops the input from the page cache, builds it in a fresh process, returns a flat row."""
    # (Imported here: main() must point `import vastray` at the run's snapshot first.)
    from vastray.pagecache import drop_page_cache

    out = workdir / f"{model.label}.vrm"
    resident = drop_page_cache(model.path)
    tag = f"{model.label} budget {budget_text(memory)} threads {threads}"
    print(f"    build {tag} (input {resident:.0%} cached after drop)", file=sys.stderr, flush=True)
    spec = {
        "input": str(model.path),
        "output": str(out),
        "memory": memory,
        "threads": threads,
        "snapshot": snapshot,
        "label": model.label,
        "compact_triangles": COMPACT_TRIANGLES[0],
    }
    row: dict[str, Any] = {
        "model": model.label,
        "family": model.family,
        "kind": kind,
        "budget_bytes": memory,
        "threads": threads,
        "input_path": str(model.path),
        "format": model.path.suffix.lower(),
        "input_bytes": model.path.stat().st_size,
        "input_resident_after_drop": resident,
    }
    try:
        report, seen = run_child(spec)
    except BuildFailedError as exc:
        print(f"    FAILED {tag}: {str(exc).splitlines()[-1]}", file=sys.stderr, flush=True)
        row["error"] = str(exc).splitlines()[-1] if str(exc) else "failed"
        return row
    finally:
        out.unlink(missing_ok=True)
    phases = report.get("phase_seconds", {})
    tris = int(report["triangles"])
    voxels = report["voxels_one"] + report["voxels_six"]
    row.update(
        {
            "triangles": tris,
            "input_triangles": int(report["input_triangles"]),
            "seconds": float(report["seconds"]),
            "mtris_s": report["input_triangles"] / report["seconds"] / 1e6,
            "mtris_s_process": report["input_triangles"] / seen["process_s"] / 1e6,
            **{f"{p}_s": float(phases.get(p, 0.0)) for p in ("scan", "read", "split", "build", "write")},
            "kd_build_s": report["kd_build_ms"] / 1000.0,
            "emit_s": report["emit_ms"] / 1000.0,
            "parts": report.get("incore_parts", report["parts"]),  # in-core pieces (older reports: "parts")
            "ooc_levels": report["out_of_core_levels"],
            "incore_limit": report["incore_limit"],
            "peak_rss_bytes": int(report["peak_rss_bytes"]),
            "file_bytes": int(report["file_bytes"]),
            "raw_bytes": int(report["raw_bytes"]),
            "bytes_per_triangle": float(report["bytes_per_triangle"]),
            "compression_ratio": float(report["compression_ratio"]),
            "refs_per_triangle": report["references"] / max(1, tris),
            "voxels": voxels,
            "voxels_one_pct": 100.0 * report["voxels_one"] / max(1, voxels),
            "node_levels": report["node_levels"],
            "blocks": report["blocks"],
            "max_depth": report["max_depth"],
            "degenerate": report["degenerate"],
            "warnings": "; ".join(report.get("warnings", [])),
            **sampled_peaks(report.get("sampled_rss_peaks", {})),
            "cpu_build_s": report["cpu_all_threads_s"],
            "cpu_main_thread_s": report["cpu_main_thread_s"],
            "speedup_bound": report["cpu_all_threads_s"] / max(1e-9, report["cpu_main_thread_s"]),
            **seen,
            "cpu_per_wall": (seen["cpu_user_s"] + seen["cpu_sys_s"]) / seen["process_s"],
        }
    )
    print(
        f"    -> {report['seconds']:.1f} s ({row['mtris_s']:.2f} Mtri/s; "
        + ", ".join(f"{p} {v:.1f}" for p, v in phases.items())
        + f"), peak RSS {row['peak_rss_bytes'] / MiB:.0f} MiB, {row['bytes_per_triangle']:.1f} B/tri, "
        f"{row['parts']} part(s), {row['ooc_levels']} out-of-core level(s)",
        file=sys.stderr,
        flush=True,
    )
    return row


def sampled_peaks(peaks: dict[str, dict[str, int]]) -> dict[str, Any]:
    """Flattens the child's sampled per-phase peaks: overall anonymous and file-backed
    peaks, the phase of the anonymous peak, and the anonymous peak of each phase."""
    out: dict[str, Any] = {"peak_anon_bytes": math.nan, "peak_file_bytes": math.nan, "peak_anon_phase": ""}
    if not peaks:
        return out
    anon = {phase: p.get("RssAnon", 0) for phase, p in peaks.items()}
    top = max(anon, key=lambda k: anon[k])
    out["peak_anon_bytes"] = anon[top]
    out["peak_anon_phase"] = top
    out["peak_file_bytes"] = max(p.get("RssFile", 0) for p in peaks.values())
    for phase in ("scan", "read", "split", "build", "write"):
        out[f"peak_anon_{phase}_bytes"] = anon.get(phase, math.nan)
        out[f"peak_file_{phase}_bytes"] = peaks.get(phase, {}).get("RssFile", math.nan)
    return out


def best(rows: list[dict[str, Any]]) -> dict[str, Any]:
    ok = [r for r in rows if "error" not in r]
    if not ok:
        return rows[0]
    chosen = dict(min(ok, key=lambda r: r["seconds"]))
    chosen["runs"] = len(rows)
    return chosen


def bench_model(
    model: Model,
    args: argparse.Namespace,
    nt: int,
    snapshot: str,
    workdir: Path,
    min_budget: int,
    index: int,
) -> list[dict[str, Any]]:
    rows: list[dict[str, Any]] = []
    scaling = model.family != "real" and model.requested in args.scaling_sizes and nt > 1
    main_runs: list[dict[str, Any]] = []
    t1_runs: list[dict[str, Any]] = []
    base_runs: list[dict[str, Any]] = []
    baseline = args.baseline_package and model.family != "real"
    for rep in range(args.reps):
        # The one-thread and all-thread builds (and the baseline's) run back to back,
        # alternating which goes first, so slow spells of the shared machine hit all alike.
        order = ["main", "t1", "baseline"] if (index + rep) % 2 == 0 else ["baseline", "t1", "main"]
        for kind in order:
            if kind == "main":
                main_runs.append(one_build(model, "main", args.memory, nt, snapshot, workdir))
            elif kind == "t1" and scaling:
                t1_runs.append(one_build(model, "t1", args.memory, 1, snapshot, workdir))
            elif kind == "baseline" and baseline:
                base_runs.append(
                    one_build(model, "baseline", args.memory, nt, args.baseline_package, workdir)
                )
    rows.append(best(main_runs))
    if base_runs:
        rows.append(best(base_runs))
    if t1_runs:
        t1 = best(t1_runs)
        t1["first"] = "t1" if index % 2 else "all"
        rows.append(t1)
    if not args.no_ooc:
        memory = ooc_budget(model.triangles, args.ooc_fraction, min_budget)
        from vastray.build import BuildOptions

        if memory < args.memory and BuildOptions(memory=memory).incore_limit() < model.triangles:
            runs = [one_build(model, "ooc", memory, nt, snapshot, workdir) for _ in range(args.reps)]
            rows.append(best(runs))
        else:
            print(f"    {model.label}: too small to force out of core; skipped", file=sys.stderr)
    return rows


# ----------------------------------------------------------------------------- report


def mib(x: Any) -> str:
    return fmt(x / MiB, 0) if isinstance(x, (int, float)) and math.isfinite(x) else "n/a"


def main_table(rows: list[dict[str, Any]]) -> str:
    headers = [
        "model",
        "triangles",
        "budget",
        "threads",
        "parts",
        "ooc levels",
        "total s",
        "Mtri/s",
        "scan s",
        "read s",
        "split s",
        "build s",
        "write s",
        "kd build s",
        "emit s",
        "peak RSS MiB",
        "file MiB",
        "B/tri",
        "compr.",
        "refs/tri",
        "1-sample voxel %",
    ]
    body = []
    for r in rows:
        if r["kind"] in ("t1", "baseline"):
            continue
        if "error" in r:
            head = [r["model"], "n/a", budget_text(r["budget_bytes"]), str(r["threads"]), "FAILED"]
            body.append(head + ["-"] * (len(headers) - len(head)))
            continue
        body.append(
            [
                r["model"],
                f"{r['triangles']:,}",
                budget_text(r["budget_bytes"]),
                str(r["threads"]),
                str(r["parts"]),
                str(r["ooc_levels"]),
                fmt(r["seconds"]),
                fmt(r["mtris_s"], 3),
                fmt(r["scan_s"]),
                fmt(r["read_s"]),
                fmt(r["split_s"]),
                fmt(r["build_s"]),
                fmt(r["write_s"]),
                fmt(r["kd_build_s"]),
                fmt(r["emit_s"]),
                mib(r["peak_rss_bytes"]),
                fmt(r["file_bytes"] / MiB, 1),
                fmt(r["bytes_per_triangle"], 1),
                fmt(r["compression_ratio"]) + "x",
                fmt(r["refs_per_triangle"]),
                fmt(r["voxels_one_pct"], 1),
            ]
        )
    return markdown_table(headers, body)


def within(peak: float, budget: int, overhead: int) -> str:
    if not math.isfinite(peak):
        return "n/a"
    if peak <= budget:
        return "yes"
    return "with overhead" if peak <= budget + overhead else "**no**"


def memory_table(rows: list[dict[str, Any]], baselines: dict[str, dict[str, int]]) -> str:
    from vastray.build import STATED_OVERHEAD_BYTES

    headers = [
        "model",
        "budget",
        "threads",
        "peak RSS MiB (child)",
        "peak RSS MiB (parent wait4)",
        "RSS - idle child MiB",
        "peak anon MiB",
        "anon - idle child MiB",
        "anon peak in",
        "peak file-backed MiB",
        "budget + overhead MiB",
        "RSS within",
        "anon within",
    ]
    body = []
    for r in rows:
        if "error" in r or r["kind"] == "baseline":
            continue
        base = baselines["streamed"]
        budget = r["budget_bytes"]
        body.append(
            [
                r["model"],
                budget_text(budget),
                str(r["threads"]),
                mib(r["peak_rss_bytes"]),
                mib(r["wait4_maxrss_bytes"]),
                mib(r["peak_rss_bytes"] - base["rss"]),
                mib(r["peak_anon_bytes"]),
                mib(r["peak_anon_bytes"] - base["anon"]),
                r["peak_anon_phase"] or "n/a",
                mib(r["peak_file_bytes"]),
                mib(budget + STATED_OVERHEAD_BYTES),
                within(r["peak_rss_bytes"], budget, STATED_OVERHEAD_BYTES),
                within(r["peak_anon_bytes"], budget, STATED_OVERHEAD_BYTES),
            ]
        )
    return markdown_table(headers, body)


def io_table(rows: list[dict[str, Any]]) -> str:
    headers = [
        "model",
        "budget",
        "threads",
        "input MiB",
        "cached after drop %",
        "disk read MiB",
        "disk write MiB",
        "process s",
        "CPU s",
        "CPU/wall",
    ]
    body = []
    for r in rows:
        if "error" in r or r["kind"] == "baseline":
            continue
        body.append(
            [
                r["model"],
                budget_text(r["budget_bytes"]),
                str(r["threads"]),
                fmt(r["input_bytes"] / MiB, 1),
                fmt(100 * r["input_resident_after_drop"], 1),
                mib(r["disk_read_bytes"]),
                mib(r["disk_write_bytes"]),
                fmt(r["process_s"]),
                fmt(r["cpu_user_s"] + r["cpu_sys_s"], 1),
                fmt(r["cpu_per_wall"]),
            ]
        )
    return markdown_table(headers, body)


def scaling_table(rows: list[dict[str, Any]], nt: int) -> str:
    by_model: dict[str, dict[str, dict[str, Any]]] = {}
    for r in rows:
        if "error" not in r and r["kind"] in ("main", "t1"):
            by_model.setdefault(r["model"], {})[r["kind"]] = r
    headers = ["model", "triangles", "1T s", f"{nt}T s", "**speedup**", "1T Mtri/s", f"{nt}T Mtri/s"]
    headers += ["scan", "read", "split", "build", "write", "kd build", "emit", "ran first"]
    headers += [f"{nt}T CPU s", f"{nt}T main-thread CPU s", f"{nt}T speedup bound"]
    body = []
    for model, pair in by_model.items():
        if "t1" not in pair or "main" not in pair:
            continue
        one, many = pair["t1"], pair["main"]

        def ratio(key: str, one: dict[str, Any] = one, many: dict[str, Any] = many) -> str:
            a, b = one[key], many[key]
            return f"{a / b:.2f}x" if b > 0.005 and math.isfinite(a / b) else "-"

        body.append(
            [
                model,
                f"{one['triangles']:,}",
                fmt(one["seconds"]),
                fmt(many["seconds"]),
                "**" + ratio("seconds") + "**",
                fmt(one["mtris_s"], 3),
                fmt(many["mtris_s"], 3),
                ratio("scan_s"),
                ratio("read_s"),
                ratio("split_s"),
                ratio("build_s"),
                ratio("write_s"),
                ratio("kd_build_s"),
                ratio("emit_s"),
                "1T" if one.get("first") == "t1" else f"{nt}T",
                fmt(many["cpu_build_s"], 1),
                fmt(many["cpu_main_thread_s"], 1),
                fmt(many["speedup_bound"]) + "x",
            ]
        )
    return markdown_table(headers, body) if body else "(no thread-scaling pairs in this run)"


def baseline_table(rows: list[dict[str, Any]], rev: str) -> str:
    """The baseline revision's builds beside the current code's, same input and settings."""
    pairs: dict[str, dict[str, dict[str, Any]]] = {}
    for r in rows:
        if "error" not in r and r["kind"] in ("main", "baseline"):
            pairs.setdefault(r["model"], {})[r["kind"]] = r
    headers = [
        "model",
        "triangles",
        "threads",
        f"{rev} s",
        "now s",
        "**speedup**",
        f"{rev} Mtri/s",
        "now Mtri/s",
    ]
    headers += ["scan+read", "split", "build", "write", "kd build", "emit"]
    headers += [f"{rev} parts", "now parts", f"{rev} RSS MiB", "now RSS MiB", f"{rev} B/tri", "now B/tri"]
    body = []
    for model, pair in pairs.items():
        if "baseline" not in pair or "main" not in pair:
            continue
        old, new = pair["baseline"], pair["main"]

        def ratio(key: str, old: dict[str, Any] = old, new: dict[str, Any] = new) -> str:
            a, b = old[key], new[key]
            return f"{a / b:.2f}x" if b > 0.005 and math.isfinite(a / b) else "-"

        old_rs = old["scan_s"] + old["read_s"]
        new_rs = new["scan_s"] + new["read_s"]
        body.append(
            [
                model, f"{new['triangles']:,}", str(new["threads"]), fmt(old["seconds"]), fmt(new["seconds"]),
                "**" + ratio("seconds") + "**", fmt(old["mtris_s"], 3), fmt(new["mtris_s"], 3),
                f"{old_rs / new_rs:.2f}x" if new_rs > 0.005 else "-",
                ratio("split_s"), ratio("build_s"), ratio("write_s"), ratio("kd_build_s"), ratio("emit_s"),
                str(old["parts"]), str(new["parts"]), mib(old["peak_rss_bytes"]), mib(new["peak_rss_bytes"]),
                fmt(old["bytes_per_triangle"], 1), fmt(new["bytes_per_triangle"], 1),
            ]
        )  # fmt: skip
    return markdown_table(headers, body) if body else "(no baseline pairs in this run)"


def generation_table(models: list[Model]) -> str:
    body = []
    for m in models:
        if m.family == "real":
            continue
        body.append(
            [
                m.label,
                f"{m.triangles:,}",
                fmt(m.path.stat().st_size / MiB, 1),
                fmt(m.gen_seconds, 1),
                fmt(m.triangles / m.gen_seconds / 1e6 if m.gen_seconds > 0 else math.nan, 2),
                "cached" if m.cached else "this run",
            ]
        )
    headers = ["model", "triangles", "PLY MiB", "generation s", "Mtri/s", "generated"]
    return markdown_table(headers, body) if body else "(no procedural models in this run)"


def paper_tables(rows: list[dict[str, Any]]) -> str:
    quoted = markdown_table(
        [
            "Model",
            "Tris",
            "Size",
            "Compr. ratio",
            "Build time",
            "B/tri (derived)",
            "ktri/s, 1 thread (derived)",
        ],
        [
            [name, t_txt, s_txt, c_txt, b_txt, fmt(size / tris, 1), fmt(tris / secs / 1e3, 1)]
            for name, tris, size, _, secs, t_txt, s_txt, c_txt, b_txt in PAPER_TABLE6
        ],
    )
    paper = {p[0]: p for p in PAPER_TABLE6}
    mains = {r["model"]: r for r in rows if r["kind"] == "main" and "error" not in r}
    ones = {r["model"]: r for r in rows if r["kind"] == "t1" and "error" not in r}
    body = []
    for model, r in mains.items():
        analogue = ANALOGUES.get(r["family"]) or ANALOGUES.get(model)
        if analogue is None:
            continue
        _, ptris, psize, pcompr, psecs, *_ = paper[analogue]
        p_bpt = psize / ptris
        one = ones.get(model)
        rate1 = one["mtris_s"] * 1e3 if one else math.nan
        body.append(
            [
                model,
                f"{r['triangles']:,}",
                fmt(r["bytes_per_triangle"], 1),
                analogue,
                fmt(p_bpt, 1),
                f"{r['bytes_per_triangle'] / p_bpt:.2f}x",
                f"{100 / r['compression_ratio']:.0f}%",
                f"{100 * pcompr:.0f}%",
                fmt(rate1, 0),
                fmt(ptris / psecs / 1e3, 1),
                f"{rate1 / (ptris / psecs / 1e3):.0f}x" if math.isfinite(rate1) else "n/a",
            ]
        )
    ours = markdown_table(
        [
            "our model",
            "triangles",
            "our B/tri",
            "paper model",
            "paper B/tri",
            "ours / paper",
            "our compressed/raw",
            "paper compr.",
            "our ktri/s 1T",
            "paper ktri/s 1T",
            "speed ratio",
        ],
        body,
    )
    return (
        quoted
        + "\n\nOurs next to the paper (our default-budget builds; analogue by kind of geometry):\n\n"
        + ours
    )


def targets_table(rows: list[dict[str, Any]], nt: int) -> str:
    from vastray.build import STATED_OVERHEAD_BYTES

    body = []
    ok_rows = [r for r in rows if "error" not in r]
    mains = [r for r in ok_rows if r["kind"] == "main" and r["family"] in PROCEDURAL]
    for fam in PROCEDURAL:
        # The rate target is on the binary PLY inputs of 10^7 triangles (the largest below 10^8).
        fam_rows = [
            r
            for r in mains
            if r["family"] == fam and r["format"] == ".ply" and r["triangles"] < 0.95 * TARGET_BIG
        ]
        if not fam_rows:
            continue
        r = max(fam_rows, key=lambda r: r["triangles"])
        cores = "" if nt == 2 else f" (this machine: {nt} threads, not 2)"
        met = "yes" if r["mtris_s"] >= TARGET_RATE / 1e6 else "**no**"
        body.append(
            [
                f">= 1,000,000 triangles/s end to end on 2 cores{cores}",
                f"{r['model']} ({budget_text(r['budget_bytes'])}, {r['threads']}T): "
                f"{r['mtris_s']:.3f} Mtri/s by the builder's clock, "
                f"{r['mtris_s_process']:.3f} Mtri/s by process wall time "
                f"({r['mtris_s'] * 1e6 / TARGET_RATE:.0%} of the target)",
                met,
            ]
        )
    big = [
        r for r in ok_rows if r["triangles"] >= 0.95 * TARGET_BIG and r["budget_bytes"] <= TARGET_BIG_BUDGET
    ]
    for r in big:
        # Judged on the kernel's peak RSS and on the sampled anonymous peak (the RSS also
        # counts pages of memory-mapped scratch files, which the kernel can drop).
        rss, anon = r["peak_rss_bytes"], r["peak_anon_bytes"]
        verdicts = [
            f"{what}: " + within(peak, TARGET_BIG_BUDGET, STATED_OVERHEAD_BYTES).replace("**", "")
            for what, peak in (("RSS", rss), ("anon", anon))
        ]
        obj = r["format"] == ".obj"
        fast = obj or r["seconds"] <= TARGET_BIG_SECONDS
        ok = rss <= TARGET_BIG_BUDGET and fast
        goal = (
            "a 10^8-triangle OBJ within a 2 GB budget"
            if obj
            else (f"a 10^8-triangle model within a 2 GB budget in <= {TARGET_BIG_SECONDS} s")
        )
        body.append(
            [
                goal,
                f"{r['model']} ({budget_text(r['budget_bytes'])}, {r['threads']}T): peak RSS "
                f"{rss / MiB:.0f} MiB, peak anonymous {anon / MiB:.0f} MiB, in {r['seconds']:.0f} s",
                ("yes" if ok else "**no**") + " (" + "; ".join(verdicts) + ")",
            ]
        )
    if not big:
        largest = [r for r in mains if r["budget_bytes"] <= TARGET_BIG_BUDGET]
        note = ""
        if largest:
            r = max(largest, key=lambda r: r["triangles"])
            note = f"; largest here: {r['model']} at peak RSS {r['peak_rss_bytes'] / MiB:.0f} MiB"
        body.append(
            [
                "a 10^8-triangle model within a 2 GB budget",
                f"not measured in this run (add 1e8 to --sizes){note}",
                "n/a",
            ]
        )
    return markdown_table(["target", "measured", "met"], body)


def report(
    rows: list[dict[str, Any]],
    models: list[Model],
    info: dict[str, str],
    args: argparse.Namespace,
    nt: int,
    baselines: dict[str, dict[str, int]],
) -> str:
    failures = [r for r in rows if "error" in r]
    parts = [
        "# vastray build: throughput, memory and file size",
        "",
        "Each build runs in a fresh Python process (`bench/build.py --child`, which calls "
        "`vastray.build.build_model` from a copy of the package taken at the start, Python and native "
        "module, and prints its report as JSON). "
        "**Before every build the input file's pages are dropped from the OS page cache** "
        "(`fsync` + `posix_fadvise(POSIX_FADV_DONTNEED)`; the *cached after drop* column checks it "
        "with `mincore`), so the first pass reads the input from the disk; the builder's second pass "
        "over the input, and its scratch files, may come from the page cache. Procedural inputs are "
        "binary PLY files generated beforehand by `vastray scene` (cached in "
        f"`{shown_path(args.cache)}`); their generation is not part of the build time. "
        "The machine is shared and noisy: absolute seconds move from run to run; the thread-scaling "
        "ratios are measured side by side.",
        "",
        *command_and_machine(info),
        "",
        "## Targets",
        "",
        targets_table(rows, nt),
        "",
        f"## Builds (budget {budget_text(args.memory)}, and forced out of core)",
        "",
        main_table(rows),
        "",
        "*total s* is the builder's own clock (file in to file renamed, fsync included); *Mtri/s* = "
        "input triangles / total s. *scan/read/split/build/write s* are its phases (scan: text "
        "inputs parsed into staged arrays, soups' bounds pass); *kd build s* and "
        "*emit s* split the build phase: kd-tree construction (native, parallel) and the emission "
        "of treelets, voxels and triangle blocks (native, LZ4 compression and CRC included), "
        "summed over the in-core parts. *parts* = in-core parts, *ooc levels* = out-of-core "
        "treelet levels above them (each is one pass over the triangles). *peak RSS* is the child's "
        "`ru_maxrss`, the whole process (interpreter and libraries included). *B/tri* = file bytes "
        "per triangle, *compr.* = raw / stored block bytes (LZ4), *refs/tri* = triangle references "
        "in kd-tree leaves per triangle, *1-sample voxel %* = share of LOD voxels with one colour "
        "sample (the rest have six).",
        "",
        *(
            [
                f"## Before and after: {args.baseline} against the current code (same input, back to back)",
                "",
                baseline_table(rows, args.baseline),
                "",
                f"Each ratio is {args.baseline}'s time / the current code's (above 1: faster now), from "
                "builds of the same input run back to back, alternating which goes first. "
                f"{args.baseline} had no scan phase (its read phase took the bounds pass); its split "
                "phase included what is now sifted while reading.",
                "",
            ]
            if args.baseline
            else []
        ),
        "## Thread scaling (same budget, same input, one thread against all, back to back)",
        "",
        scaling_table(rows, nt),
        "",
        "Each ratio is 1-thread time / all-thread time (above 1: the threads help). On a machine "
        "that other work keeps busy the threads cannot show; the last three columns do not depend "
        "on that: the CPU seconds of the all-thread build (all threads of the child, during "
        "`build_model`), those of its main thread (all the Python: reading, splitting, "
        "plus its share of the native work), and their quotient: about the most these threads "
        "could speed the build up on idle cores, since the main thread's CPU time is a floor under "
        "the wall time and one thread would need about all of the CPU time.",
        "",
        "## Memory",
        "",
        f"An idle child (interpreter, numpy, the native module; nothing built) peaks at "
        f"{baselines['streamed']['rss'] / MiB:.0f} MiB ({baselines['streamed']['anon'] / MiB:.0f} MiB "
        "anonymous); every input streams (text formats are scanned into staged binary arrays in "
        "the scratch folder first), and the *- idle child* columns subtract it. *peak RSS* is the "
        "kernel's high-water "
        "mark (`ru_maxrss`), which counts the pages of memory-mapped files (the input, the scratch "
        "records) along with the heap; *peak anon* and *peak file-backed* are the largest `RssAnon` "
        "and `RssFile` of `/proc/self/status`, sampled every 20 ms by a thread in the child, and "
        "*anon peak in* the build phase where the anonymous peak fell. Clean file-backed pages are "
        "dropped by the kernel under memory pressure; anonymous memory is what a budget has to hold. "
        "*within*: peak <= budget (*yes*), <= budget + the builder's stated fixed overhead "
        "(*with overhead*), or neither. *parent wait4* is the same child's `ru_maxrss` as the parent "
        "sees it through `wait4` (the per-child form of `getrusage(RUSAGE_CHILDREN)`; build.csv also "
        "has the running RUSAGE_CHILDREN maximum, and the anonymous and file-backed peak of every "
        "phase).",
        "",
        memory_table(rows, baselines),
        "",
        "## I/O and CPU",
        "",
        "*cached after drop*: share of the input's pages still in the page cache after the drop "
        "(`mincore`). *disk read/write*: the child's block I/O (`ru_inblock`/`ru_oublock` x 512 B; "
        "reads the page cache served do not count). *process s*: the child's wall time, interpreter "
        "start and imports included. *CPU/wall*: user + system CPU seconds over process wall time "
        "(2.0 = both cores busy all the time).",
        "",
        io_table(rows),
        "",
        "## Generating the procedural inputs (not part of the build times)",
        "",
        generation_table(models),
        "",
        "## Paper 000 (Afra 2012), Table 6",
        "",
        "Quoted as printed (construction statistics; size of the compressed out-of-core structure; "
        "compression ratio = compressed size relative to the full uncompressed structure: kd-tree, "
        "voxels and triangles; build time single-threaded on an Intel Core i7-2600). B/tri and ktri/s "
        "are derived here (decimal GB).",
        "",
        paper_tables(rows),
        "",
        "Caveats: the paper's models are 7-354 M triangles, ours 10^4-10^7 (here bytes per "
        "triangle hardly change from 10^6 to 10^7); our *compressed/raw* is stored / raw block "
        "bytes (1 / compr.), the paper's is its compressed size over the uncompressed structure; "
        "speed ratios compare different CPUs nine years apart.",
        "",
    ]
    if failures:
        parts += ["## Failures", ""]
        for r in failures:
            setting = f"budget {budget_text(r['budget_bytes'])} threads {r['threads']}"
            parts.append(f"- {r['model']} {setting}: {r['error']}")
        parts.append("")
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


def plot(rows: list[dict[str, Any]], path: Path, title: str, nt: int) -> bool:
    plt = pyplot()
    if plt is None:
        return False

    ok = [r for r in rows if "error" not in r]
    fig, (ax_rate, ax_mem) = plt.subplots(1, 2, figsize=(13, 5.2))
    colours = {"plant": "#2171b5", "mandelbulb": "#e6550d", "real": "#31a354"}
    styles = {
        "main": ("o", "-", f"{nt}T"),
        "t1": ("s", "--", "1T"),
        "ooc": ("^", ":", f"{nt}T, small budget"),
    }
    for fam in ("real", *PROCEDURAL):
        for kind, (marker, line, desc) in styles.items():
            pts = sorted(
                (r for r in ok if r["family"] == fam and r["kind"] == kind), key=lambda r: r["triangles"]
            )
            if not pts:
                continue
            x = [r["triangles"] for r in pts]
            ls = "none" if fam == "real" else line
            label = f"{fam} {desc}"
            ax_rate.plot(
                x, [r["mtris_s"] for r in pts], marker=marker, ls=ls, color=colours[fam], label=label
            )
            if kind != "t1":
                rss = [r["peak_rss_bytes"] / MiB for r in pts]
                ax_mem.plot(x, rss, marker=marker, ls=ls, color=colours[fam], label=f"{label}: RSS")
                anon = [r.get("peak_anon_bytes", math.nan) / MiB for r in pts]
                style = {"marker": marker, "mfc": "none", "ls": ls, "lw": 0.8, "color": colours[fam]}
                ax_mem.plot(x, anon, label=f"{label}: anon", **style)
                if kind == "ooc":
                    for r in pts:
                        ax_mem.plot(
                            r["triangles"], r["budget_bytes"] / MiB, marker="_", ms=14, color=colours[fam]
                        )
    ax_rate.axhline(TARGET_RATE / 1e6, color="grey", ls="--", lw=1)
    where = {"xycoords": ("axes fraction", "data"), "va": "bottom", "fontsize": 8, "color": "grey"}
    ax_rate.annotate("target 1 Mtri/s", (0.01, TARGET_RATE / 1e6), **where)
    ax_rate.set_xscale("log")
    ax_rate.set_xlabel("triangles")
    ax_rate.set_ylabel("Mtri/s end to end (builder clock)")
    ax_rate.set_title("build throughput")
    ax_rate.grid(alpha=0.3, which="both")
    ax_rate.legend(fontsize=7, loc="upper right", bbox_to_anchor=(1.0, 0.9))
    budget = max((r["budget_bytes"] for r in ok if r["kind"] == "main"), default=0)
    if budget:
        ax_mem.axhline(budget / MiB, color="grey", ls="--", lw=1)
        ax_mem.annotate(f"budget {budget_text(budget)}", (0.01, budget / MiB), **where)
    ax_mem.set_xscale("log")
    ax_mem.set_yscale("log")
    ax_mem.set_xlabel("triangles")
    ax_mem.set_ylabel("peak MiB, whole process")
    ax_mem.set_title(
        "peak memory per build (filled: RSS, hollow: anonymous; bars: small budgets)", fontsize=10
    )
    ax_mem.grid(alpha=0.3, which="both")
    top = max([r["peak_rss_bytes"] for r in ok] + [budget], default=GiB) / MiB
    ax_mem.set_ylim(top=top * 30)  # room for the legend above the data
    ax_mem.legend(fontsize=6, ncol=2, loc="upper left")
    save_figure(fig, title, path)
    return True


# ----------------------------------------------------------------------------- main


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument(
        "--models", default="all", help="comma list: mesh stems, plant, mandelbulb, real, procedural, all"
    )
    ap.add_argument(
        "--sizes", default="1e6,1e7", help="procedural triangle counts (default 1e6,1e7; add 1e8)"
    )
    ap.add_argument("--memory", default="2G", help="the default budget (default 2G)")
    ap.add_argument(
        "--ooc-fraction",
        type=float,
        default=1 / 3,
        help="forced out-of-core budget as a share of the soup size, 36 B/triangle (default 1/3)",
    )
    ap.add_argument("--no-ooc", action="store_true", help="skip the forced out-of-core builds")
    ap.add_argument(
        "--obj-sizes",
        default="",
        help="procedural sizes also built from an OBJ copy of their PLY (e.g. 1e8; default none)",
    )
    ap.add_argument(
        "--scaling-sizes",
        default="1e6,1e7",
        help="procedural sizes that also build on one thread, for thread scaling (default 1e6,1e7)",
    )
    ap.add_argument("--threads", type=int, default=0, help="'all threads' count (default: hardware threads)")
    ap.add_argument(
        "--baseline",
        default="",
        help="a git revision whose builder runs beside the current one on the procedural models "
        "(built for the run; the before/after table)",
    )
    ap.add_argument("--reps", type=int, default=1, help="builds per setting; the fastest is kept (default 1)")
    ap.add_argument(
        "--compact-triangles",
        action="store_true",
        help="build with compact triangle blocks (docs/FORMAT.md §11a)",
    )
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument(
        "--cache", type=Path, default=DEFAULT_CACHE, help="generated inputs (default bench/.cache)"
    )
    ap.add_argument("--out", type=Path, default=RESULTS_DIR, help="output folder (default bench/results)")
    ap.add_argument("--name", default="build", help="output file stem (default build)")
    args = ap.parse_args(argv)
    from vastray.units import parse_bytes

    args.memory = parse_bytes(args.memory, "memory budget")
    args.scaling_sizes = {parse_count(x) for x in args.scaling_sizes.split(",") if x.strip()}
    args.obj_sizes = {parse_count(x) for x in args.obj_sizes.split(",") if x.strip()}
    args.cache = args.cache.resolve()
    return args


def main(argv: list[str] | None = None) -> int:
    # One copy of the package for the whole run; every child imports the same code.
    snap, snap_desc = snapshot_vastray()
    snapshot = str(snap)
    use_snapshot(snapshot)
    from vastray import native
    from vastray.build import INCORE_BYTES_PER_TRIANGLE, MIN_INCORE_TRIANGLES

    args = parse_args(argv)
    COMPACT_TRIANGLES[0] = args.compact_triangles
    args.baseline_package = ""
    if args.baseline:
        package, desc = build_baseline(args.baseline)
        args.baseline_package = str(package)
    names = [m.strip() for m in args.models.split(",") if m.strip()]
    sizes = [parse_count(s) for s in args.sizes.split(",") if s.strip()]
    nt = args.threads or native.hardware_threads()
    min_budget = MIN_INCORE_TRIANGLES * INCORE_BYTES_PER_TRIANGLE

    info = machine_info(
        {
            "vastray": snap_desc,
            **({"baseline": desc} if args.baseline else {}),
            "vastray hardware threads": str(native.hardware_threads()),
            "all-threads setting": str(nt),
            "models": str(models_dir()),
            "input cache": str(args.cache),
        }
    )
    print("\n".join(f"{k}: {v}" for k, v in info.items()), file=sys.stderr)
    start = time.perf_counter()

    print("inputs:", file=sys.stderr, flush=True)
    models = real_models(names)
    for gen in procedural_generators(names):
        for n in sizes:
            model = ensure_generated(gen, n, args.seed, args.cache, snapshot)
            models.append(model)
            if n in args.obj_sizes:
                models.append(ensure_obj(model, snapshot))
    models.sort(key=lambda m: (m.family != "real", m.triangles, m.label))

    baselines = {}
    for kind in ("streamed",):
        baseline_report, _ = run_child({"baseline": kind, "snapshot": snapshot})
        baselines[kind] = {"rss": baseline_report["peak_rss_bytes"], "anon": baseline_report["anon_bytes"]}
    info["children import"] = f"{baseline_report['build']}, {baseline_report['native']}"
    info["idle child peak RSS"] = ", ".join(
        f"{k} input {v['rss'] / MiB:.0f} MiB ({v['anon'] / MiB:.0f} MiB anon)" for k, v in baselines.items()
    )

    args.cache.mkdir(parents=True, exist_ok=True)
    workdir = Path(tempfile.mkdtemp(prefix="build-", dir=args.cache))
    rows: list[dict[str, Any]] = []
    try:
        for i, model in enumerate(models):
            print(f"[{i + 1}/{len(models)}] {model.label} ({model.triangles:,} triangles)", file=sys.stderr)
            rows += bench_model(model, args, nt, snapshot, workdir, min_budget, i)
    finally:
        shutil.rmtree(workdir, ignore_errors=True)
    info["total wall time"] = f"{time.perf_counter() - start:.0f} s"
    info["load average at end"] = ", ".join(f"{x:.2f}" for x in os.getloadavg())

    text = report(rows, models, info, args, nt, baselines)
    print(text)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / f"{args.name}.md").write_text(text)
    write_csv(rows, args.out / f"{args.name}.csv")
    plotted = plot(rows, args.out / f"{args.name}.png", f"vastray build, {info['cpu']}, {nt} threads", nt)
    print(f"wrote {args.out / args.name}.md, .csv{', .png' if plotted else ''}", file=sys.stderr)
    return 1 if any("error" in r for r in rows) else 0


if __name__ == "__main__":
    if len(sys.argv) > 2 and sys.argv[1] == CHILD_FLAG:
        raise SystemExit(child_main(sys.argv[2]))
    if len(sys.argv) > 4 and sys.argv[1] == OBJ_FLAG:
        use_snapshot(sys.argv[2])
        write_obj(Path(sys.argv[3]), Path(sys.argv[4]))
        raise SystemExit(0)
    if len(sys.argv) > 2 and sys.argv[1] == CLI_FLAG:
        use_snapshot(sys.argv[2])
        from vastray.cli import main as vastray_main

        raise SystemExit(vastray_main(sys.argv[3:]))
    raise SystemExit(main())
