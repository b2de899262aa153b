"""What memory costs the first time it is written: a machine property every other table
here depends on.

Not a test. Maps anonymous memory, writes it once (every page faults and is zeroed by
the kernel first), writes it again (resident: the plain write rate), unmaps it, and maps
and writes the same amount again at once and after an idle wait. On bare metal the first
write runs at a few GB/s. A virtual machine whose balloon device reports free pages to
its host (VIRTIO_BALLOON_F_REPORTING) gives freed memory back; writing it again then
waits for the host as well. Writes firsttouch.md to bench/results/.

    python bench/firsttouch.py --sizes 256M,1G,4G --waits 0,5,30 --copy bench/.cache/plant-1e8-s1.ply

With --copy FILE it also copies FILE (read from the page cache) into a new file beside
it, alternately through the page cache (copy_file_range, then fsync: the build's write
phase before direct_io.py) and past it (direct_io.DirectFile, as the build writes now).
"""

from __future__ import annotations

import argparse
import mmap
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from common import RESULTS_DIR, machine_info, markdown_table

from vastray.direct_io import DirectFile
from vastray.units import parse_bytes

REPORTING_BIT = 5  # VIRTIO_BALLOON_F_REPORTING in the device's feature bits


def balloon_reports_free_pages() -> str:
    found = sorted(Path("/sys/bus/virtio/drivers/virtio_balloon").glob("virtio*/features"))
    if not found:
        return "no virtio balloon"
    bits = found[0].read_text().strip()
    return "yes" if len(bits) > REPORTING_BIT and bits[REPORTING_BIT] == "1" else "no"


def write_rate(size: int, again: bool = False) -> tuple[float, float]:
    """GB/s of the first write of a fresh mapping of `size` bytes, and (again) of a
    second write of it; the mapping is gone on return."""
    m = mmap.mmap(-1, size, flags=mmap.MAP_PRIVATE | mmap.MAP_ANONYMOUS)
    a = np.frombuffer(m, np.uint8)
    start = time.perf_counter()
    a.fill(1)
    first = size / (time.perf_counter() - start) / 1e9
    second = float("nan")
    if again:
        start = time.perf_counter()
        a.fill(2)
        second = size / (time.perf_counter() - start) / 1e9
    del a
    m.close()
    return first, second


def copy_seconds(src: Path, direct: bool) -> float:
    """Seconds to copy `src` into a new file and make it durable, one way or the other."""
    dst = src.with_name(f".{src.name}.copy-test")
    size = src.stat().st_size
    fd = os.open(src, os.O_RDONLY)
    try:
        start = time.perf_counter()
        if direct:
            with DirectFile(dst) as out:
                out.copy(fd, 0, size)
        else:
            out_fd = os.open(dst, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
            try:
                done = 0
                while done < size:
                    done += os.copy_file_range(fd, out_fd, min(size - done, 64 << 20), done)
                os.fsync(out_fd)
            finally:
                os.close(out_fd)
        return time.perf_counter() - start
    finally:
        os.close(fd)
        dst.unlink(missing_ok=True)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sizes", default="256M,1G,2G")
    ap.add_argument("--waits", default="0,5,20", help="idle seconds before mapping again")
    ap.add_argument("--copy", type=Path, help="a large file to copy both ways")
    ap.add_argument("--rounds", type=int, default=2, help="copies each way (with --copy)")
    ap.add_argument("--out", type=Path, default=RESULTS_DIR)
    ap.add_argument("--name", default="firsttouch")
    args = ap.parse_args()
    sizes = [parse_bytes(s, "size") for s in args.sizes.split(",")]
    waits = [float(w) for w in args.waits.split(",")]
    rows = []
    for size in sizes:
        first, resident = write_rate(size, again=True)
        row = [f"{size / 2**20:.0f}", f"{first:.2f}", f"{resident:.2f}"]
        for wait in waits:
            time.sleep(wait)
            row.append(f"{write_rate(size)[0]:.2f}")
        rows.append(row)
        print(" | ".join(row), flush=True)
    headers = ["MiB", "first write GB/s", "resident GB/s", *(f"again after {w:g} s GB/s" for w in waits)]
    copies = []
    if args.copy is not None:
        with open(args.copy, "rb") as f:  # into the page cache, as the level files are
            while f.read(64 << 20):
                pass
        size = args.copy.stat().st_size
        for r in range(args.rounds):
            for direct in (False, True) if r % 2 == 0 else (True, False):
                seconds = copy_seconds(args.copy, direct)
                way = "past the page cache (DirectFile)" if direct else "copy_file_range + fsync"
                copies.append([way, f"{size / 2**30:.2f}", f"{seconds:.2f}", f"{size / seconds / 1e9:.2f}"])
                print(" | ".join(copies[-1]), flush=True)
                time.sleep(3)
    info = machine_info({"balloon reports free pages": balloon_reports_free_pages()})
    text = (
        "# First writes of memory against writes of resident memory\n\n"
        "Anonymous mappings written with numpy's fill; each *again* column unmaps the memory, "
        "waits, maps as much again and writes it once. The machine is shared: read the ratios.\n\n"
        "## Machine\n\n" + "\n".join(f"- {k}: {v}" for k, v in info.items()) + "\n\n"
        "## Write rates\n\n" + markdown_table(headers, rows) + "\n"
    )
    if copies:
        text += (
            f"\n## Copying {args.copy.name} (from the page cache) into a new, durable file\n\n"
            + markdown_table(["way", "GiB", "seconds", "GB/s"], copies)
            + "\n"
        )
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / f"{args.name}.md").write_text(text)
    print(f"wrote {args.out / (args.name + '.md')}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
