"""Helpers shared by the benchmarks in bench/: machine description, timing, memory
high-water marks, camera rays built exactly like the renderer builds them, and tables.

Benchmarks run on shared, noisy machines, so every helper here is meant for measurements
taken side by side in one process: report ratios of interleaved runs, not absolute times.
"""

from __future__ import annotations

import datetime as _dt
import math
import os
import platform
import re
import shlex
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path
from typing import Any, TypeVar

import numpy as np

T = TypeVar("T")

REPO_ROOT = Path(__file__).resolve().parent.parent
RESULTS_DIR = Path(__file__).resolve().parent / "results"


# ----------------------------------------------------------------------------- machine


def cpu_model() -> str:
    """The CPU model name from /proc/cpuinfo (Linux), else what platform reports."""
    try:
        text = Path("/proc/cpuinfo").read_text()
    except OSError:
        return platform.processor() or platform.machine()
    match = re.search(r"^model name\s*:\s*(.+)$", text, re.MULTILINE)
    return match.group(1).strip() if match else (platform.processor() or platform.machine())


def git_revision() -> str:
    """Short commit id of the working tree, with '+dirty' when it has local changes."""
    try:
        rev = subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"], cwd=REPO_ROOT, capture_output=True, text=True, check=True
        ).stdout.strip()
        dirty = subprocess.run(
            ["git", "status", "--porcelain", "--untracked-files=no"],
            cwd=REPO_ROOT,
            capture_output=True,
            text=True,
            check=True,
        ).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"
    return rev + ("+dirty" if dirty else "")


def machine_info(extra: dict[str, str] | None = None) -> dict[str, str]:
    """Everything a reader needs to interpret the numbers of one benchmark run."""
    info: dict[str, str] = {
        "date": _dt.datetime.now().astimezone().isoformat(timespec="seconds"),
        "command": " ".join(shlex.quote(a) for a in [Path(sys.executable).name, *sys.argv]),
        "cpu": cpu_model(),
        "logical cores": str(os.cpu_count()),
        "python": platform.python_version(),
        "numpy": np.__version__,
        "platform": platform.platform(),
        "git": git_revision(),
    }
    try:
        import psutil

        info["physical cores"] = str(psutil.cpu_count(logical=False))
        info["memory"] = f"{psutil.virtual_memory().total / 2**30:.1f} GiB"
        load = os.getloadavg()
        info["load average at start"] = ", ".join(f"{x:.2f}" for x in load)
    except (ImportError, OSError):
        pass
    if extra:
        info.update(extra)
    return info


# ----------------------------------------------------------------------------- native


def pin_native() -> str:
    """Load `vastray.native` from a private copy of the extension module and return a
    description of it (path, size, modification time).

    An editable install rebuilds the extension in place; a long benchmark that has the
    file mapped would crash if someone rebuilds it meanwhile, and would measure a mix of
    builds if it imported late. The copy pins one build for the whole run.
    """
    import atexit
    import importlib.util
    import shutil
    import tempfile

    spec = importlib.util.find_spec("vastray.native")
    if spec is None or spec.origin is None:
        raise ImportError("vastray.native is not built (pip install --no-build-isolation -e .)")
    if "vastray.native" in sys.modules:
        raise RuntimeError("pin_native() must run before vastray.native is imported")
    origin = Path(spec.origin)
    stamp = _dt.datetime.fromtimestamp(origin.stat().st_mtime).astimezone().isoformat(timespec="seconds")
    folder = Path(tempfile.mkdtemp(prefix="vastray-bench-"))
    atexit.register(shutil.rmtree, folder, ignore_errors=True)
    copy = folder / origin.name
    shutil.copy2(origin, copy)
    pinned = importlib.util.spec_from_file_location("vastray.native", copy)
    assert pinned is not None and pinned.loader is not None
    module = importlib.util.module_from_spec(pinned)
    sys.modules["vastray.native"] = module
    pinned.loader.exec_module(module)
    import vastray

    vastray.native = module  # type: ignore[attr-defined]
    return f"{origin} ({origin.stat().st_size:,} bytes, built {stamp}), run from a private copy"


# ----------------------------------------------------------------------------- models


def models_dir() -> Path:
    """The folder of real test meshes: $VASTRAY_MODELS, else ../shared/models."""
    env = os.environ.get("VASTRAY_MODELS")
    return Path(env) if env else (REPO_ROOT.parent / "shared" / "models")


def parse_count(text: str) -> int:
    """'1e6', '1000000' or '1M' -> 1000000."""
    t = text.strip().lower()
    scale = {"k": 1e3, "m": 1e6, "g": 1e9}.get(t[-1:], 1.0)
    if t[-1:] in "kmg":
        t = t[:-1]
    value = float(t) * scale
    if not math.isfinite(value) or value < 1:
        raise ValueError(f"not a positive count: {text!r}")
    return round(value)


def format_count(n: int) -> str:
    """1000000 -> '1e6'; other numbers as plain integers."""
    exp = math.log10(n) if n > 0 else 0.0
    return f"1e{round(exp)}" if n > 0 and abs(exp - round(exp)) < 1e-9 else str(n)


# ----------------------------------------------------------------------------- timing


def timed(fn: Callable[[], T]) -> tuple[float, T]:
    """(wall seconds, result) of one call."""
    start = time.perf_counter()
    result = fn()
    return time.perf_counter() - start, result


class Best:
    """Keeps the smallest of repeated measurements (the least disturbed by other load)."""

    def __init__(self) -> None:
        self.values: list[float] = []

    def add(self, seconds: float) -> None:
        self.values.append(seconds)

    @property
    def best(self) -> float:
        return min(self.values) if self.values else math.nan

    @property
    def median(self) -> float:
        return float(np.median(self.values)) if self.values else math.nan


# ----------------------------------------------------------------------------- memory


def _status_kib(field: str) -> int | None:
    try:
        text = Path("/proc/self/status").read_text()
    except OSError:
        return None
    match = re.search(rf"^{field}:\s*(\d+)\s*kB", text, re.MULTILINE)
    return int(match.group(1)) if match else None


def current_rss() -> int:
    """Resident set size of this process in bytes."""
    kib = _status_kib("VmRSS")
    if kib is not None:
        return kib * 1024
    import psutil

    return int(psutil.Process().memory_info().rss)


class PeakRss:
    """Peak resident memory of this process while the `with` block runs, minus the RSS on
    entry (`delta` bytes after exit).

    On Linux the kernel's high-water mark (VmHWM) is reset on entry through
    /proc/self/clear_refs and read on exit, which sees every page even when the work
    holds the GIL. Elsewhere a psutil thread samples RSS every few milliseconds.
    """

    def __init__(self, interval: float = 0.005) -> None:
        self.interval = interval
        self.start = 0
        self.peak = 0
        self._use_hwm = False
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def __enter__(self) -> PeakRss:
        self.start = current_rss()
        try:
            Path("/proc/self/clear_refs").write_text("5")
            self._use_hwm = _status_kib("VmHWM") is not None
        except OSError:
            self._use_hwm = False
        self.peak = self.start
        if not self._use_hwm:
            self._thread = threading.Thread(target=self._sample, daemon=True)
            self._thread.start()
        return self

    def _sample(self) -> None:
        while not self._stop.wait(self.interval):
            self.peak = max(self.peak, current_rss())

    def __exit__(self, *exc: object) -> None:
        if self._use_hwm:
            hwm = _status_kib("VmHWM")
            self.peak = max(self.peak, (hwm or 0) * 1024, current_rss())
        else:
            self._stop.set()
            if self._thread is not None:
                self._thread.join()
            self.peak = max(self.peak, current_rss())

    @property
    def delta(self) -> int:
        return max(0, self.peak - self.start)


# ----------------------------------------------------------------------------- rays


def camera_rays(
    eye: Sequence[float],
    target: Sequence[float],
    up: Sequence[float],
    fov: float,
    width: int,
    height: int,
) -> tuple[np.ndarray, np.ndarray]:
    """Primary rays of a pinhole camera in pixel order, exactly as the native renderer
    computes them (see `vastray.camera.Camera.primary_rays`). Returns (origins,
    directions), each (W*H, 3) float64."""
    from vastray.camera import Camera

    def as_vec(a: Sequence[float]) -> tuple[float, float, float]:
        return (float(a[0]), float(a[1]), float(a[2]))

    return Camera(as_vec(eye), as_vec(target), as_vec(up), fov, width, height).primary_rays()


def orthonormal_basis(n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit tangents (s, t) for each unit normal in n (Duff et al. 2017, branchless)."""
    sign = np.where(n[:, 2] >= 0.0, 1.0, -1.0)
    a = -1.0 / (sign + n[:, 2])
    b = n[:, 0] * n[:, 1] * a
    s = np.stack([1.0 + sign * n[:, 0] ** 2 * a, sign * b, -sign * n[:, 0]], axis=1)
    t = np.stack([b, sign + n[:, 1] ** 2 * a, -n[:, 1]], axis=1)
    return s, t


def cosine_hemisphere(normals: np.ndarray, samples: int, rng: np.random.Generator) -> np.ndarray:
    """`samples` cosine-weighted unit directions about each normal (Malley's method).

    Returns (len(normals) * samples, 3): the samples of one normal are consecutive, as
    when a renderer shoots them pixel by pixel.
    """
    m = normals.shape[0]
    r = np.sqrt(rng.random((m, samples)))
    phi = 2.0 * math.pi * rng.random((m, samples))
    lx, ly = r * np.cos(phi), r * np.sin(phi)
    lz = np.sqrt(np.maximum(0.0, 1.0 - lx * lx - ly * ly))
    s, t = orthonormal_basis(normals)
    d = lx[..., None] * s[:, None, :] + ly[..., None] * t[:, None, :] + lz[..., None] * normals[:, None, :]
    d /= np.linalg.norm(d, axis=2, keepdims=True)
    return d.reshape(-1, 3)


def facing_normals(tri: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit geometric normals of triangles `tri` (T,3,3) turned towards the incoming rays,
    and a mask of the non-degenerate ones."""
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    length = np.linalg.norm(n, axis=1)
    ok = length > 0
    n[ok] /= length[ok, None]
    flip = np.einsum("ij,ij->i", n, dirs) > 0
    n[flip] = -n[flip]
    return n, ok


# The benchmarks' distant light: the direction of every shadow ray.
SHADOW_DIRECTION = np.array([0.3, 0.8, 0.5]) / np.linalg.norm([0.3, 0.8, 0.5])


def shadow_rays_from(ao_origins: np.ndarray, samples: int) -> tuple[np.ndarray, np.ndarray]:
    """The shadow rays of the benchmarks (bench/rays.py's shadow table, bench/ab.py's shadow
    workload): one from each hit point of ao_rays_from_hits (which repeats a point for its
    `samples` rays), unbounded, along SHADOW_DIRECTION. Returns origins, directions."""
    origins = np.ascontiguousarray(ao_origins[:: max(1, samples)])
    return origins, np.ascontiguousarray(np.broadcast_to(SHADOW_DIRECTION, origins.shape))


def ao_rays_from_hits(
    vertices: np.ndarray,
    faces: np.ndarray,
    dirs: np.ndarray,
    hits: dict[str, Any],
    samples: int,
    rng: np.random.Generator,
    diagonal: float,
) -> tuple[np.ndarray, np.ndarray, float]:
    """The ambient-occlusion rays of the benchmarks: from every primary hit of a batch
    intersect (`hits`: prim, u, v of the rays `dirs`) on a non-degenerate triangle,
    `samples` cosine-weighted directions about the normal facing the eye, from the hit
    point pushed off the surface by a bound on float32 error (Embree sees float32
    geometry), with tmax = 0.2 x the scene diagonal. Returns origins, directions, tmax."""
    prim = np.asarray(hits["prim"], dtype=np.int64)
    idx = np.flatnonzero(prim >= 0)
    tri = vertices[faces[prim[idx]]]  # (H, 3, 3) float64
    normals, ok = facing_normals(tri, dirs[idx])
    idx, tri, normals = idx[ok], tri[ok], normals[ok]
    u = np.asarray(hits["u"], dtype=np.float64)[idx, None]
    v = np.asarray(hits["v"], dtype=np.float64)[idx, None]
    points = tri[:, 0] * (1.0 - u - v) + tri[:, 1] * u + tri[:, 2] * v
    offset = 64.0 * np.finfo(np.float32).eps * np.abs(tri).max(axis=(1, 2)) + 1e-6 * diagonal
    origins = np.repeat(points + normals * offset[:, None], samples, axis=0)
    return origins, cosine_hemisphere(normals, samples, rng), 0.2 * diagonal


# ----------------------------------------------------------------------------- output


K = TypeVar("K")
FrameKey = tuple[K, str, float]  # (model key, view, PoE)


def alternating_frames(
    models: dict[K, Any], cameras: dict[str, Any], poes: Sequence[float], frames: int
) -> tuple[dict[FrameKey[K], list[float]], dict[FrameKey[K], Any], dict[FrameKey[K], Any], int]:
    """Out-of-core frames of several builds side by side. For each view and PoE, every
    model's complete frame (render_complete), then `frames` timed frames of each, the
    models taking turns so that the machine's load falls on all alike. Returns, keyed by
    (model key, view, PoE), the timed frames' milliseconds, the complete frames and the
    last timed frames, and how many timed frames found data missing (a cache too small
    for all the models)."""
    ms: dict[FrameKey[K], list[float]] = {}
    complete: dict[FrameKey[K], Any] = {}
    last: dict[FrameKey[K], Any] = {}
    incomplete = 0
    for view, camera in cameras.items():
        for poe in poes:
            for key, model in models.items():
                complete[key, view, poe] = model.render_complete(camera, pixels_of_error=poe)
            for _ in range(frames):
                for key, model in models.items():
                    f = model.render(camera, pixels_of_error=poe)
                    ms.setdefault((key, view, poe), []).append(f.stats.milliseconds)
                    last[key, view, poe] = f
                    incomplete += not f.stats.complete
            print(f"  {view} PoE {poe:g} done", file=sys.stderr, flush=True)
    return ms, complete, last, incomplete


def command_and_machine(info: dict[str, str]) -> list[str]:
    """The report sections that say how a benchmark was run and on what."""
    machine = [f"- {k}: {v}" for k, v in info.items() if k != "command"]
    return ["## Command", "", "```sh", info["command"], "```", "", "## Machine", "", *machine]


def markdown_sections(*sections: tuple[str, str, str]) -> list[str]:
    """Report lines for (heading, intro, table) sections; an empty intro is left out."""
    out: list[str] = []
    for heading, intro, table in sections:
        out += [f"## {heading}", "", *([intro, ""] if intro else []), table, ""]
    return out


def markdown_table(headers: Sequence[str], rows: Iterable[Sequence[Any]]) -> str:
    """A GitHub-flavoured markdown table; numbers right-aligned."""
    body = [[str(c) for c in row] for row in rows]
    align = []
    for i in range(len(headers)):
        numeric = all(_looks_numeric(r[i]) for r in body if i < len(r)) and body
        align.append("---:" if numeric else "---")
    lines = ["| " + " | ".join(headers) + " |", "| " + " | ".join(align) + " |"]
    lines += ["| " + " | ".join(r) + " |" for r in body]
    return "\n".join(lines)


def _looks_numeric(text: str) -> bool:
    core = text.strip().strip("*")
    return bool(re.fullmatch(r"[-+]?[\d.,]+(e[-+]?\d+)?[x%]?|n/a|-|nan", core, re.IGNORECASE))


def fmt(value: float, digits: int = 2) -> str:
    """A number for a table: fixed digits, 'n/a' for NaN."""
    if value is None or not math.isfinite(value):
        return "n/a"
    return f"{value:.{digits}f}"


def pyplot() -> Any | None:
    """matplotlib's pyplot on the Agg backend, or None (with a note) where the `bench`
    extra is not installed: the tables are the results, the plots only show them."""
    try:
        import matplotlib
    except ImportError:
        print("matplotlib is not installed (pip install '.[bench]'): no plot", file=sys.stderr)
        return None
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def save_figure(fig: Any, title: str, path: Path) -> None:
    """Titles, lays out, writes (PNG, 110 dpi) and closes a matplotlib figure."""
    import matplotlib.pyplot as plt

    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def geometric_mean(values: Iterable[float]) -> float:
    vals = [v for v in values if v is not None and math.isfinite(v) and v > 0]
    return math.exp(sum(math.log(v) for v in vals) / len(vals)) if vals else math.nan
