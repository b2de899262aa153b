"""Rules of the native sources that no answer shows when broken.

A prefetch the compiler drops changes no answer, only speed: GCC drops the calls to a
helper that does nothing but `__builtin_prefetch` (it finds it free of side effects),
which cost the in-core walks 10-19 % for two days of December 2026 and had emptied the
voxel-error pass's prefetch entirely. So every prefetch goes through `prefetch_line`
(native/include/vastray/prefetch.h), a volatile asm statement the compiler must keep."""

from __future__ import annotations

import re
from pathlib import Path

NATIVE = Path(__file__).resolve().parents[1] / "native"
RAW_PREFETCH = re.compile(r"__builtin_prefetch\s*\(|_mm_prefetch\s*\(")


def native_sources() -> list[Path]:
    return sorted(p for p in NATIVE.rglob("*") if p.suffix in {".h", ".hpp", ".cpp", ".cc"})


def test_prefetches_go_through_prefetch_line() -> None:
    sources = native_sources()
    assert any(p.name == "traverse_packet.h" for p in sources)  # the walk: found, and read below
    offenders = [
        f"{p.relative_to(NATIVE)}:{n}: {line.strip()}"
        for p in sources
        if p.name != "prefetch.h"
        for n, line in enumerate(p.read_text().splitlines(), 1)
        if RAW_PREFETCH.search(line.split("//")[0])
    ]
    assert not offenders, "prefetch through prefetch_line (vastray/prefetch.h):\n" + "\n".join(offenders)
    uses = sum(p.read_text().count("prefetch_line(") for p in sources if p.name != "prefetch.h")
    assert uses >= 10  # the walks' prefetches are there to be checked


def test_prefetch_line_is_kept_by_the_compiler() -> None:
    header = (NATIVE / "include" / "vastray" / "prefetch.h").read_text()
    body = header[header.index("inline void prefetch_line") :]
    kept = re.search(r"asm\s+volatile\s*\(\s*\"prefetcht0", body)
    assert kept, "prefetch_line must be a volatile asm on x86"
