"""vastray.direct_io.DirectFile: the build's output written past the page cache.

Whatever the mix of writes and copies, and wherever the buffer boundaries fall, the
file holds exactly the bytes given, in order, at their size (the tail is padded for
O_DIRECT and cut back). Where O_DIRECT is refused, at open or at the first write, it
writes through the page cache instead, with the same result, and a build gives the same
model either way.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

from vastray import direct_io
from vastray.build import BuildOptions, build_model
from vastray.direct_io import DirectFile
from vastray.modelfile import ModelFile

BUFFER = 8 << 20


def _pieces(rng: np.random.Generator, src: Path) -> tuple[list[tuple[str, int, int]], bytes]:
    """A script of writes and copies (from `src`) across several buffer boundaries, and
    the bytes it should produce."""
    source = rng.integers(0, 256, 3 * BUFFER + 12345, dtype=np.uint8).tobytes()
    src.write_bytes(source)
    script: list[tuple[str, int, int]] = []
    expected = bytearray()
    sizes = [1, 4095, 4096, 4097, BUFFER - 3, BUFFER, 2 * BUFFER + 7, 0, 300_000, 17]
    for i, n in enumerate(sizes):
        if i % 2:
            at = int(rng.integers(0, len(source) - n + 1))
            script.append(("copy", at, n))
            expected += source[at : at + n]
        else:
            script.append(("write", i, n))
            expected += bytes([i % 251 + 1]) * n
    return script, bytes(expected)


def _run(script: list[tuple[str, int, int]], src: Path, out: Path) -> int:
    fd = os.open(src, os.O_RDONLY)
    try:
        with DirectFile(out) as f:
            for kind, a, n in script:
                if kind == "copy":
                    f.copy(fd, a, n)
                else:
                    assert f.write(bytes([a % 251 + 1]) * n) == n
            size = f.size
    finally:
        os.close(fd)
    return size


def test_writes_and_copies_land_in_order_at_their_size(tmp_path: Path) -> None:
    script, expected = _pieces(np.random.default_rng(1), tmp_path / "src.bin")
    size = _run(script, tmp_path / "src.bin", tmp_path / "out.bin")
    assert size == len(expected)
    assert (tmp_path / "out.bin").read_bytes() == expected


def test_a_file_system_refusing_direct_writes_gets_the_same_bytes(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Some file systems take the O_DIRECT flag at open and refuse the writes (EINVAL):
    the writer clears the flag and goes on through the page cache. (Linux's own tmpfs
    now takes direct writes, so the refusal is injected here.)"""
    import errno
    import fcntl

    script, expected = _pieces(np.random.default_rng(2), tmp_path / "src.bin")
    real = os.pwritev
    refused = []

    def pwritev(fd: int, buffers: list, offset: int) -> int:
        if direct_io._O_DIRECT and fcntl.fcntl(fd, fcntl.F_GETFL) & direct_io._O_DIRECT:
            refused.append(offset)
            raise OSError(errno.EINVAL, "Invalid argument")
        return real(fd, buffers, offset)

    monkeypatch.setattr(direct_io.os, "pwritev", pwritev)
    assert _run(script, tmp_path / "src.bin", tmp_path / "out.bin") == len(expected)
    assert (tmp_path / "out.bin").read_bytes() == expected
    if direct_io._O_DIRECT:
        assert refused == [0]  # refused once, then written through the page cache


def test_direct_writes_on_the_test_folder(tmp_path: Path) -> None:
    """Where the test folder's file system takes O_DIRECT (ext4, xfs), the writer uses it."""
    if not direct_io._O_DIRECT:
        pytest.skip("no O_DIRECT on this platform")
    with DirectFile(tmp_path / "probe.bin") as f:
        f.write(b"x" * 10)
        used = f.direct
    assert (tmp_path / "probe.bin").read_bytes() == b"x" * 10
    if not used:
        pytest.skip("the test folder's file system refuses O_DIRECT")


def test_a_copy_past_the_end_of_its_source_is_an_error(tmp_path: Path) -> None:
    (tmp_path / "src.bin").write_bytes(b"abc")
    fd = os.open(tmp_path / "src.bin", os.O_RDONLY)
    try:
        with pytest.raises(RuntimeError, match="ends 7 bytes early"), DirectFile(tmp_path / "out.bin") as f:
            f.copy(fd, 0, 10)
    finally:
        os.close(fd)


def test_a_model_written_through_the_page_cache_is_the_same(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The build's write phase with O_DIRECT and without it (as on a tmpfs): one model."""
    source = "scene:plant:30000:1"
    options = BuildOptions(memory=8 << 20)
    build_model(source, tmp_path / "direct.vast", options)
    monkeypatch.setattr(direct_io, "_O_DIRECT", 0)
    build_model(source, tmp_path / "cached.vast", options)
    assert (tmp_path / "direct.vast").read_bytes() == (tmp_path / "cached.vast").read_bytes()
    with ModelFile(tmp_path / "direct.vast") as model:
        model.verify()


def test_a_failed_write_raises_the_systems_error(tmp_path: Path) -> None:
    """A write that fails (here: a full device), whether a full buffer's or the tail's at
    close, raises its own error: closing after it neither hides that error nor leaks the
    descriptor."""
    full = Path("/dev/full")
    if not full.exists():
        pytest.skip("no /dev/full")
    import errno

    before = len(os.listdir("/proc/self/fd"))
    for size in (BUFFER + 10, 10):  # a buffer's flush, the tail
        with pytest.raises(OSError) as raised, DirectFile(full) as f:
            f.write(b"x" * size)
        assert raised.value.errno == errno.ENOSPC
    assert len(os.listdir("/proc/self/fd")) == before


@pytest.mark.parametrize("keep", [0, 4096, 5000, BUFFER + 123])
def test_appending_keeps_the_start_and_cuts_the_rest(tmp_path: Path, keep: int) -> None:
    """`append_at` keeps the file's first bytes, writes on from there (the page it
    starts in rewritten whole) and cuts whatever the old file had past the new end, also
    when nothing is appended; `write_at` puts whole pages in front."""
    rng = np.random.default_rng(keep)
    old = rng.integers(0, 256, 2 * BUFFER + 999, dtype=np.uint8).tobytes()
    new = rng.integers(0, 256, 7777, dtype=np.uint8).tobytes()
    page = rng.integers(0, 256, 4096, dtype=np.uint8).tobytes()
    path = tmp_path / "f.bin"
    for tail in (new, b""):
        path.write_bytes(old)
        with DirectFile(path, append_at=keep) as f:
            if keep >= 8192:
                f.write_at(4096, page)
            f.write(tail)
            assert f.size == keep + len(tail)
        expected = bytearray(old[:keep] + tail)
        if keep >= 8192:
            expected[4096:8192] = page
        assert path.read_bytes() == bytes(expected)
    with pytest.raises(ValueError, match="whole 4096-byte pages"), DirectFile(path, append_at=keep) as f:
        f.write_at(100, page)


# A file system that takes O_DIRECT at open and refuses direct writes, for the whole
# process, native code included: a preloaded library whose pwrite and pwritev answer
# EINVAL on a descriptor opened with O_DIRECT, and log which call was refused.
_REFUSING_SHIM = r"""
#define _GNU_SOURCE
#include <dlfcn.h>
#include <errno.h>
#include <fcntl.h>
#include <stdio.h>
#include <stdlib.h>
#include <sys/uio.h>
#include <unistd.h>

static int refuse(int fd, const char* call) {
    if (!(fcntl(fd, F_GETFL) & O_DIRECT)) return 0;
    FILE* log = fopen(getenv("REFUSED_LOG"), "a");
    if (log) { fprintf(log, "%s\n", call); fclose(log); }
    errno = EINVAL;
    return 1;
}
#define NEXT(name) ((__typeof__(&name))dlsym(RTLD_NEXT, #name))
ssize_t pwrite(int fd, const void* b, size_t n, off_t at) {
    return refuse(fd, "pwrite") ? -1 : NEXT(pwrite)(fd, b, n, at);
}
ssize_t pwrite64(int fd, const void* b, size_t n, off_t at) {
    return refuse(fd, "pwrite") ? -1 : NEXT(pwrite64)(fd, b, n, at);
}
ssize_t pwritev(int fd, const struct iovec* v, int n, off_t at) {
    return refuse(fd, "pwritev") ? -1 : NEXT(pwritev)(fd, v, n, at);
}
ssize_t pwritev64(int fd, const struct iovec* v, int n, off_t at) {
    return refuse(fd, "pwritev") ? -1 : NEXT(pwritev64)(fd, v, n, at);
}
ssize_t pwritev2(int fd, const struct iovec* v, int n, off_t at, int flags) {
    return refuse(fd, "pwritev") ? -1 : NEXT(pwritev2)(fd, v, n, at, flags);
}
ssize_t pwritev64v2(int fd, const struct iovec* v, int n, off_t at, int flags) {
    return refuse(fd, "pwritev") ? -1 : NEXT(pwritev64v2)(fd, v, n, at, flags);
}
"""

_BUILD = """
import sys
from vastray.build import BuildOptions, build_model
report = build_model("scene:plant:120000:3", sys.argv[1], BuildOptions(memory=64 << 20, threads=2))
assert report["blocks_in_place"], report
"""


@pytest.mark.skipif(not direct_io._O_DIRECT, reason="no O_DIRECT on this platform")
def test_a_build_where_every_direct_write_is_refused_makes_the_same_model(tmp_path: Path) -> None:
    """The native block appender (build phase) and DirectFile (write phase) both meet
    the refusal, fall back to the page cache, and the model is the one a direct build
    writes. Linux's tmpfs takes direct writes now, so the refusal comes from a library
    preloaded into a build in its own process."""
    import shutil
    import subprocess
    import sys
    import sysconfig

    compiler = shutil.which((sysconfig.get_config_var("CC") or "cc").split()[0]) or shutil.which("cc")
    assert compiler, "a C compiler (the native module needs one to build)"
    (tmp_path / "shim.c").write_text(_REFUSING_SHIM)
    shim = tmp_path / "refuse_direct.so"
    subprocess.run([compiler, "-shared", "-fPIC", "-O1", "-o", shim, tmp_path / "shim.c", "-ldl"], check=True)

    def build(name: str, preload: bool) -> bytes:
        env = dict(os.environ, REFUSED_LOG=str(tmp_path / "refused.log"))
        if preload:
            env["LD_PRELOAD"] = str(shim)
        out = tmp_path / f"{name}.vast"
        subprocess.run([sys.executable, "-c", _BUILD, out], check=True, env=env, cwd=tmp_path)
        return out.read_bytes()

    direct = build("direct", preload=False)
    assert not (tmp_path / "refused.log").exists()
    refused = build("refused", preload=True)
    calls = (tmp_path / "refused.log").read_text().split()
    # Each writer was refused once (the first direct write), then wrote through the cache.
    if not calls:
        pytest.skip("the test folder's file system refuses O_DIRECT at open")
    assert sorted(set(calls)) == ["pwrite", "pwritev"] and len(calls) == 2, calls
    assert refused == direct
