"""Block cache slots on 2 MiB transparent huge pages against 4 KiB pages, side by side.

Not a test. Opens the same model in two caches of the same budget, one asking for huge
pages (BlockCache(huge_pages=True), the default) and one not, loads the 1280x720
overview to completion in each, then renders warm frames alternately from the two
(same camera, same pixels of error), so both see the same machine. Reports the median
and best frame time of each and their ratio, and how much of the process's anonymous
memory the kernel put on huge pages. Writes hugepages.md to bench/results/.

    python bench/hugepages.py --sizes 1e7,1e8 --poes 0,2 --frames 9
"""

from __future__ import annotations

import argparse
import math
import statistics
import sys
import time
from dataclasses import dataclass
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from common import RESULTS_DIR, fmt, machine_info, markdown_table
from tradeoff import built_model, isa_path

from vastray import native
from vastray.camera import frame_bounds
from vastray.outofcore import OutOfCoreModel
from vastray.units import parse_bytes


def anon_huge_mib() -> float:
    for line in Path("/proc/self/smaps_rollup").read_text().splitlines():
        if line.startswith("AnonHugePages:"):
            return int(line.split()[1]) / 1024
    return 0.0


@dataclass
class Result:
    seconds: dict[bool, list[float]]  # warm frame times, huge pages asked for or not
    granted: bool  # the kernel took the advice
    working_set_mib: float
    anon_huge_mib: float


def measure(path: Path, poe: float, frames: int, budget: int) -> Result:
    caches = {huge: native.BlockCache(budget, 2, "count", huge_pages=huge) for huge in (True, False)}
    models = {huge: OutOfCoreModel(path, cache) for huge, cache in caches.items()}
    try:
        camera = frame_bounds(*models[True].bounds, width=1280, height=720)
        for model in models.values():
            model.render_complete(camera, pixels_of_error=poe)
        times: dict[bool, list[float]] = {True: [], False: []}
        for i in range(frames):
            order = (True, False) if i % 2 == 0 else (False, True)
            for huge in order:
                start = time.perf_counter()
                frame = models[huge].render(camera, pixels_of_error=poe)
                times[huge].append(time.perf_counter() - start)
                assert frame.complete
        return Result(times, caches[True].huge_pages, frame.stats.working_set_bytes / 2**20, anon_huge_mib())
    finally:
        for model in models.values():
            model.close()


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", default="1e7,1e8")
    ap.add_argument("--poes", default="0,2")
    ap.add_argument("--frames", type=int, default=9)
    ap.add_argument("--cache", default="3G")
    ap.add_argument("--out", type=Path, default=RESULTS_DIR)
    args = ap.parse_args()
    rows = []
    for size in (int(float(s)) for s in args.sizes.split(",")):
        path = built_model(size)
        for poe in (float(p) for p in args.poes.split(",")):
            r = measure(path, poe, args.frames, parse_bytes(args.cache))
            huge_ms, small_ms = (1000 * statistics.median(r.seconds[k]) for k in (True, False))
            row = [
                f"plant 10^{round(math.log10(size))}",
                fmt(poe, 0),
                fmt(r.working_set_mib, 0),
                fmt(small_ms, 1),
                fmt(huge_ms, 1),
                fmt(1000 * min(r.seconds[False]), 1),
                fmt(1000 * min(r.seconds[True]), 1),
                f"**{small_ms / huge_ms:.3f}x**",
                "yes" if r.granted else "no",
                fmt(r.anon_huge_mib, 0),
            ]
            rows.append(row)
            print(" | ".join(row), flush=True)
    headers = [
        "model", "PoE", "working set MiB", "4 KiB pages ms", "huge pages ms", "4 KiB best ms",
        "huge best ms", "speed-up (medians)", "granted", "AnonHugePages MiB",
    ]  # fmt: skip
    info = machine_info({"ISA path": isa_path()})
    text = [
        "# Block cache slots on transparent huge pages",
        "",
        __doc__.split("\n\n")[1].replace("\n", " "),
        "",
        "## Machine",
        "",
        *(f"- {k}: {v}" for k, v in info.items()),
        "",
        "## Warm 1280x720 overview frames, medians of alternating frames",
        "",
        markdown_table(headers, rows),
        "",
    ]
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "hugepages.md").write_text("\n".join(text))
    print(f"wrote {args.out / 'hugepages.md'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
