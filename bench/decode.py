"""Block decode throughput: what a fetcher thread does per block (read the stored bytes,
check the CRC-32, decode LZ4), each stage timed for each implementation side by side.

Not a test. Builds a few models (procedural plant and mandelbulb, a real mesh) into the
bench cache, compiles bench/decode/decode_blocks.cpp against liblz4, libdeflate and
zlib (baseline x86-64 flags, as a portable wheel is built), and runs it on each model:

* read, cold (the model's pages dropped from the page cache) and warm (page cache);
* CRC-32 of the stored bytes: vastray's former slicing-by-4 tables
  (bench/decode/handwritten_codec.cpp), zlib's crc32, libdeflate's libdeflate_crc32;
* LZ4 block decode: vastray's former decoder and liblz4's LZ4_decompress_safe;
* the whole fetch through the module's own ModelIndex::read_block (what the block cache
  runs: pread + CRC + LZ4, through the libraries the module links now).

Every stage runs over all blocks of the model once per pass, the implementations
interleaved within each pass; the fastest pass of each is kept. Writes decode.md and
decode.csv to bench/results/.

    python bench/decode.py [--passes 7] [--sizes 1e6]
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import shutil
import subprocess
import sys
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))

from common import (
    REPO_ROOT,
    RESULTS_DIR,
    command_and_machine,
    fmt,
    format_count,
    machine_info,
    markdown_table,
    models_dir,
    parse_count,
)

from build import write_csv  # bench/build.py

BENCH_DIR = Path(__file__).resolve().parent
CACHE = BENCH_DIR / ".cache" / "decode"
SOURCES = [
    BENCH_DIR / "decode" / "decode_blocks.cpp",
    BENCH_DIR / "decode" / "handwritten_codec.cpp",
    REPO_ROOT / "native" / "src" / "model_index.cpp",
    REPO_ROOT / "native" / "src" / "crc32.cpp",
    REPO_ROOT / "native" / "src" / "lz4.cpp",
]
MiB = 1 << 20


def compile_tool(out: Path) -> list[str]:
    """Compiles the benchmark; returns the command used."""
    flags = [
        "-O3",
        "-std=c++17",
        "-DNDEBUG",
        f"-I{REPO_ROOT / 'native' / 'include'}",
        f"-I{BENCH_DIR / 'decode'}",
    ]
    libs = ["-llz4", "-ldeflate", "-lz"]
    pkg = shutil.which("pkg-config")
    if pkg:
        found = subprocess.run(
            [pkg, "--cflags", "--libs", "liblz4", "libdeflate", "zlib"], capture_output=True, text=True
        )
        if found.returncode == 0:
            libs = found.stdout.split()
    cmd = [os.environ.get("CXX", "c++"), *flags, *map(str, SOURCES), *libs, "-o", str(out)]
    subprocess.run(cmd, check=True)
    return cmd


def ensure_model(source: str, name: str) -> Path:
    """The model built from `source` in the bench cache, built when missing."""
    from vastray.build import BuildOptions, build_model

    CACHE.mkdir(parents=True, exist_ok=True)
    path = CACHE / f"{name}.vast"
    if not path.is_file():
        print(f"  building {name} from {source}", file=sys.stderr, flush=True)
        build_model(source, path, BuildOptions())
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)  # dirty pages cannot be dropped for the cold reads
    finally:
        os.close(fd)
    return path


def run(tool: Path, model: Path, passes: int) -> dict[str, Any]:
    out = subprocess.run([str(tool), str(model), str(passes)], capture_output=True, text=True, check=True)
    return json.loads(out.stdout)


def row(name: str, r: dict[str, Any]) -> dict[str, Any]:
    n = r["blocks"]
    per_block = {k[:-2]: 1e6 * v / n for k, v in r.items() if k.endswith("_s")}
    stored, raw = r["stored_bytes"] / MiB, r["raw_bytes"] / MiB
    lz4_raw = r["lz4_raw_bytes"] / MiB
    return {
        "model": name,
        "blocks": n,
        "lz4_blocks": r["lz4_blocks"],
        "stored_mib": stored,
        "raw_mib": raw,
        **{f"{k}_us_per_block": v for k, v in per_block.items()},
        "read_cold_mib_s": stored / r["read_cold_s"],
        "read_warm_mib_s": stored / r["read_warm_s"],
        "crc_vastray_mib_s": stored / r["crc_vastray_s"],
        "crc_zlib_mib_s": stored / r["crc_zlib_s"],
        "crc_libdeflate_mib_s": stored / r["crc_libdeflate_s"],
        "lz4_vastray_mib_s": lz4_raw / r["lz4_vastray_s"],
        "lz4_liblz4_mib_s": lz4_raw / r["lz4_liblz4_s"],
        "fetch_module_mib_s": raw / r["fetch_module_s"],
        # What one warm fetch costs with each pair of implementations (read + CRC + LZ4).
        "fetch_old_us": per_block["read_warm"] + per_block["crc_vastray"] + per_block["lz4_vastray"],
        "fetch_libs_us": per_block["read_warm"] + per_block["crc_libdeflate"] + per_block["lz4_liblz4"],
    }


def report(rows: list[dict[str, Any]], info: dict[str, str], tool_cmd: list[str], passes: int) -> str:
    stages = markdown_table(
        [
            "model",
            "blocks",
            "stored MiB",
            "raw MiB",
            "read cold",
            "read warm",
            "CRC vastray (old)",
            "CRC zlib",
            "CRC libdeflate",
            "LZ4 vastray (old)",
            "LZ4 liblz4",
            "whole fetch (module)",
        ],
        [
            [r["model"], f"{r['blocks']:,}", fmt(r["stored_mib"], 1), fmt(r["raw_mib"], 1)]
            + [
                fmt(r[f"{k}_us_per_block"], 1)
                for k in (
                    "read_cold",
                    "read_warm",
                    "crc_vastray",
                    "crc_zlib",
                    "crc_libdeflate",
                    "lz4_vastray",
                    "lz4_liblz4",
                    "fetch_module",
                )
            ]
            for r in rows
        ],
    )
    rates = markdown_table(
        [
            "model",
            "CRC vastray (old)",
            "CRC zlib",
            "CRC libdeflate",
            "libdeflate / old",
            "LZ4 vastray (old)",
            "LZ4 liblz4",
            "liblz4 / old",
            "fetch, old codecs (µs)",
            "fetch, libraries (µs)",
            "old / libraries",
        ],
        [
            [
                r["model"],
                fmt(r["crc_vastray_mib_s"], 0),
                fmt(r["crc_zlib_mib_s"], 0),
                fmt(r["crc_libdeflate_mib_s"], 0),
                f"{r['crc_libdeflate_mib_s'] / r['crc_vastray_mib_s']:.1f}x",
                fmt(r["lz4_vastray_mib_s"], 0),
                fmt(r["lz4_liblz4_mib_s"], 0),
                f"{r['lz4_liblz4_mib_s'] / r['lz4_vastray_mib_s']:.1f}x",
                fmt(r["fetch_old_us"], 1),
                fmt(r["fetch_libs_us"], 1),
                f"{r['fetch_old_us'] / r['fetch_libs_us']:.2f}x",
            ]
            for r in rows
        ],
    )
    return "\n".join(
        [
            "# Block decode throughput: read + CRC-32 + LZ4 per block",
            "",
            "What a fetcher thread does for every block it loads, stage by stage, for each "
            "implementation side by side in one process (`bench/decode/decode_blocks.cpp`, compiled "
            "with baseline x86-64 flags as a portable wheel is). *vastray (old)* is the CRC-32 (slicing "
            "by 4) and LZ4 decoder the native module had before it linked libdeflate and liblz4 "
            "(`bench/decode/handwritten_codec.cpp`). Each stage runs over all blocks once per pass, "
            f"the implementations interleaved; the fastest of {passes} passes is kept. *read cold*: the "
            "model's pages dropped from the page cache first; *whole fetch (module)*: "
            "`ModelIndex::read_block` (pread + CRC + LZ4), the block cache's own path, now through "
            "the libraries.",
            "",
            *command_and_machine(info),
            f"- compiled with: `{' '.join(shlex.quote(c) for c in tool_cmd[:5])} ...`",
            "",
            "## Microseconds per block",
            "",
            stages,
            "",
            "## Throughput (MiB/s; CRC of the stored bytes, LZ4 of the decoded bytes) and ratios",
            "",
            rates,
            "",
            "The module uses libdeflate's CRC-32 (it picks a carry-less-multiply kernel at run "
            "time where the CPU has one) and liblz4's safe decoder (fuzzed upstream). Both come "
            "from the distribution: `liblz4-dev` and `libdeflate-dev` to build, `liblz4-1` and "
            "`libdeflate0` to run.",
            "",
        ]
    )


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--passes", type=int, default=7)
    ap.add_argument("--sizes", default="1e6", help="procedural triangle counts (default 1e6)")
    ap.add_argument("--out", type=Path, default=RESULTS_DIR)
    ap.add_argument("--name", default="decode")
    args = ap.parse_args(argv)
    info = machine_info()
    tool = CACHE / "decode_blocks"
    CACHE.mkdir(parents=True, exist_ok=True)
    tool_cmd = compile_tool(tool)
    models: list[tuple[str, Path]] = []
    for size in (parse_count(s) for s in args.sizes.split(",") if s.strip()):
        for scene in ("plant", "mandelbulb"):
            name = f"{scene}-{format_count(size)}"
            models.append((name, ensure_model(f"scene:{scene}:{size}:1", name)))
    for mesh in ("nefertiti.obj", "stanford-bunny.obj"):
        path = models_dir() / mesh
        if path.is_file():
            models.append((path.stem, ensure_model(str(path), path.stem)))
    rows = []
    for name, path in models:
        print(f"  {name}: {args.passes} passes", file=sys.stderr, flush=True)
        rows.append(row(name, run(tool, path, args.passes)))
    text = report(rows, info, tool_cmd, args.passes)
    print(text)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / f"{args.name}.md").write_text(text)
    write_csv(rows, args.out / f"{args.name}.csv")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
