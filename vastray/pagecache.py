"""How much of a file the OS page cache holds, and dropping it: what a cold start means.

The benchmarks drop a model's pages before they time a cold open, and the tests check
that the block cache's read-ahead reaches the page cache. Linux (mmap + mincore, which
touch no page; posix_fadvise).
"""

from __future__ import annotations

import ctypes
import math
import os
from pathlib import Path


def resident_fraction(path: Path) -> float:
    """Share of the file's pages in the OS page cache (mmap + mincore; NaN if unsupported)."""
    size = path.stat().st_size
    if size == 0:
        return 0.0
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        libc.mmap.restype = ctypes.c_void_p
        c_int = ctypes.c_int
        libc.mmap.argtypes = [ctypes.c_void_p, ctypes.c_size_t, c_int, c_int, c_int, ctypes.c_long]
        libc.munmap.argtypes = [ctypes.c_void_p, ctypes.c_size_t]
        libc.mincore.argtypes = [ctypes.c_void_p, ctypes.c_size_t, ctypes.c_void_p]
        page = os.sysconf("SC_PAGE_SIZE")
        fd = os.open(path, os.O_RDONLY)
        try:
            addr = libc.mmap(None, size, 1, 1, fd, 0)  # PROT_READ, MAP_SHARED; touches no page
        finally:
            os.close(fd)
        if addr is None or addr == ctypes.c_void_p(-1).value:
            return math.nan
        try:
            pages = (size + page - 1) // page
            vec = (ctypes.c_ubyte * pages)()
            if libc.mincore(addr, size, vec) != 0:
                return math.nan
            return sum(b & 1 for b in bytes(vec)) / pages
        finally:
            libc.munmap(addr, size)
    except (OSError, AttributeError, ValueError):
        return math.nan


def drop_page_cache(path: Path) -> float:
    """Evicts the file's pages from the page cache (fsync, then POSIX_FADV_DONTNEED), so
    the next read comes from the disk. Returns the share still resident afterwards."""
    fd = os.open(path, os.O_RDONLY)
    try:
        try:
            os.fsync(fd)  # dirty pages cannot be dropped
        except OSError:
            pass  # read-only file system: nothing is dirty
        os.posix_fadvise(fd, 0, 0, os.POSIX_FADV_DONTNEED)
    finally:
        os.close(fd)
    return resident_fraction(path)
