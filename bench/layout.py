"""Does the order of a model's blocks in its file change how fast a view loads?

Not a test. A build leaves its blocks in the order it made them (docs/FORMAT.md §3);
every model before that had them in id order, each level's streams one after the
other. This copies a built model into id order beside it
(`model_assembly.rewrite_in_id_order`), then, alternating between the two files, drops
each from the page cache and opens it cold in a fresh block cache and renders the
overview until complete: the seconds from open to complete, the bytes read, the working
set. Writes bench/results/NAME.md (`--name`, default `layout`).

    python bench/layout.py MODEL [--reps 4] [--image 1280x720] [--poe 2]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from common import RESULTS_DIR, command_and_machine, machine_info, markdown_table

from vastray.camera import frame_bounds
from vastray.model_assembly import rewrite_in_id_order
from vastray.outofcore import OutOfCoreModel, make_cache
from vastray.pagecache import drop_page_cache

HEADERS = ["layout", "runs", "seconds", "median s", "read MiB", "working set MiB", "cached after drop"]


def cold_overview(path: Path, width: int, height: int, poe: float) -> dict[str, float]:
    dropped = drop_page_cache(path)
    start = time.perf_counter()
    cache = make_cache(4 << 30)
    with OutOfCoreModel(path, cache) as model:
        camera = frame_bounds(*model.bounds, width=width, height=height)
        done = model.render_complete(camera, pixels_of_error=poe)
        return {
            "seconds": time.perf_counter() - start,
            "frames": done.frames,
            "read_mib": cache.totals()["bytes_read"] / 2**20,
            "working_set_mib": done.stats.working_set_bytes / 2**20,
            "cached_after_drop": dropped,
        }


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("model", type=Path, help="a built model (vastray build)")
    parser.add_argument("--reps", type=int, default=4)
    parser.add_argument("--image", default="1280x720")
    parser.add_argument("--poe", type=float, default=2.0, help="pixels of error")
    parser.add_argument("--name", default="layout")
    args = parser.parse_args()
    width, height = (int(x) for x in args.image.split("x"))
    copy = args.model.with_name(f".{args.model.name}.in-id-order")
    print(f"writing {copy} ...", file=sys.stderr, flush=True)
    rewrite_in_id_order(args.model, copy)
    runs: dict[str, list[dict[str, float]]] = {"as built": [], "in id order": []}
    try:
        for rep in range(args.reps):
            order = [("as built", args.model), ("in id order", copy)]
            for label, path in order if rep % 2 == 0 else order[::-1]:
                runs[label].append(cold_overview(path, width, height, args.poe))
                r = runs[label][-1]
                line = f"  {label}: {r['seconds']:.2f} s, {r['read_mib']:.0f} MiB read"
                print(line, file=sys.stderr, flush=True)
    finally:
        copy.unlink(missing_ok=True)

    rows = []
    for label, results in runs.items():
        seconds = [r["seconds"] for r in results]
        rows.append(
            [
                label,
                len(results),
                f"{min(seconds):.2f}-{max(seconds):.2f}",
                f"{statistics.median(seconds):.2f}",
                f"{results[0]['read_mib']:.0f}",
                f"{results[0]['working_set_mib']:.0f}",
                f"{max(r['cached_after_drop'] for r in results):.3f}",
            ]
        )
    info = machine_info({"command": " ".join(["python", *sys.argv]), "model": str(args.model)})
    text = "\n".join(
        [
            "# Block order in the file and the cold load of an overview",
            "",
            __doc__.split("\n\n")[1].replace("\n", " "),
            "",
            *command_and_machine(info),
            "",
            f"## {width}x{height} overview at PoE {args.poe:g}, cold open to complete",
            "",
            markdown_table(HEADERS, rows),
            "",
        ]
    )
    out = RESULTS_DIR / f"{args.name}.md"
    out.write_text(text)
    print(text)
    print(f"wrote {out}", file=sys.stderr)


if __name__ == "__main__":
    main()
