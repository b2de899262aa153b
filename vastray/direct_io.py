"""Writing a new file past the page cache (O_DIRECT), for the model builder's output.

The write phase of a build puts gigabytes into a new file: the header, the index, and
the blocks of the level files. Through the page cache each of those pages is first
memory the kernel must find and fill, then dirty data that fsync waits for; where
memory that was freed comes back slowly (a virtual machine whose host takes back freed
pages: bench/results/firsttouch.md) that can cost more than the disk. On the 2-core
machine of bench/results the 10^8 build's write phase took 4.7-4.9 s this way against
19.7 s through the page cache (bench/results/build-1e8-direct.md).

`DirectFile` gathers what it is given in an 8 MiB page-aligned buffer and
writes whole buffers at aligned offsets; the tail goes out padded to 4 KiB and the file
is then cut to its size. Where the file system refuses O_DIRECT, at open or at the
first write (older tmpfs, some FUSE and network file systems), the same writes go
through the page cache instead: the same bytes either way.
"""

from __future__ import annotations

import errno
import fcntl
import mmap
import os

_BUFFER = 8 << 20
_ALIGN = 4096  # covers 512-byte and 4 KiB logical blocks
_O_DIRECT = getattr(os, "O_DIRECT", 0)


class DirectFile:
    """A file written front to back: a new one, or an existing one from a given byte
    on. `close()` makes it durable (fsync) and returns its size; on an error the caller
    removes the file."""

    def __init__(self, path: str | os.PathLike[str], append_at: int | None = None) -> None:
        """A new file; or, with `append_at`, the existing file `path` kept up to that
        byte and written on from there (its first bytes are left as they are)."""
        flags = os.O_WRONLY | os.O_CREAT | getattr(os, "O_CLOEXEC", 0)
        if append_at is None:
            flags |= os.O_TRUNC
        self.direct = False
        if _O_DIRECT:
            try:
                self._fd = os.open(path, flags | _O_DIRECT, 0o644)
                self.direct = True
            except OSError as e:
                if e.errno != errno.EINVAL:
                    raise
        if not self.direct:
            self._fd = os.open(path, flags, 0o644)
        self._buffer = mmap.mmap(-1, _BUFFER)  # page-aligned, as O_DIRECT wants
        self._view = memoryview(self._buffer)
        self._fill = 0  # bytes of the buffer in use
        self._offset = 0  # where the buffer goes in the file (a multiple of _ALIGN)
        self._closed = False
        self._cut = append_at is not None  # the file may run past what is written: cut it
        if append_at:
            # Direct writes start on a page: the bytes of the last page before
            # `append_at` are read back into the buffer and written again with it.
            self._offset = append_at - append_at % _ALIGN
            with open(path, "rb") as f:
                kept = os.pread(f.fileno(), append_at - self._offset, self._offset)
            if len(kept) != append_at - self._offset:
                self._release()
                raise RuntimeError(f"{path}: shorter than the {append_at} bytes to append to")
            self.write(kept)

    @property
    def size(self) -> int:
        return self._offset + self._fill

    def write(self, data: bytes | bytearray | memoryview) -> int:
        src = memoryview(data).cast("B")
        done = 0
        while done < len(src):
            n = min(len(src) - done, _BUFFER - self._fill)
            self._view[self._fill : self._fill + n] = src[done : done + n]
            self._fill += n
            done += n
            if self._fill == _BUFFER:
                self._flush_buffer()
        return done

    def copy(self, fd: int, offset: int, size: int) -> None:
        """Appends `size` bytes at `offset` of the open file `fd`, read straight into the
        buffer."""
        while size > 0:
            want = min(size, _BUFFER - self._fill)
            n = os.preadv(fd, [self._view[self._fill : self._fill + want]], offset)
            if n == 0:
                raise RuntimeError(f"the file to copy ends {size} bytes early (at byte {offset})")
            self._fill += n
            offset += n
            size -= n
            if self._fill == _BUFFER:
                self._flush_buffer()

    def write_at(self, offset: int, data: bytes | bytearray | memoryview) -> None:
        """Writes `data` at `offset`, both a multiple of 4096 bytes, apart from the
        appending (the region must lie before what is appended)."""
        if offset % _ALIGN or len(data) % _ALIGN:
            raise ValueError("write_at takes whole 4096-byte pages")
        aligned = mmap.mmap(-1, len(data))  # page-aligned, as O_DIRECT wants
        try:
            view = memoryview(aligned)
            view[:] = memoryview(data).cast("B")
            self._write_at(view, offset)
            view.release()
        finally:
            aligned.close()

    def close(self) -> int:
        """Writes what is left, fsyncs, closes; returns the file's size."""
        if self._closed:
            return self.size
        try:
            size = self.size
            if self._fill:
                padded = -(-self._fill // _ALIGN) * _ALIGN
                self._view[self._fill : padded] = bytes(padded - self._fill)
                self._write_at(self._view[:padded], self._offset)
            if self._fill or self._cut:
                os.ftruncate(self._fd, size)
            os.fsync(self._fd)
            return size
        finally:
            self._release()

    def abort(self) -> None:
        """Closes without finishing (the caller removes the file)."""
        if not self._closed:
            self._release()

    def __enter__(self) -> DirectFile:
        return self

    def __exit__(self, kind: object, *_: object) -> None:
        if kind is None:
            self.close()
        else:
            self.abort()

    def _release(self) -> None:
        self._closed = True
        self._view.release()
        try:
            self._buffer.close()
        except BufferError:
            # A view of the buffer is still held (by the traceback of a failed write):
            # the mapping goes with the last of them.
            pass
        os.close(self._fd)

    def _flush_buffer(self) -> None:
        self._write_at(self._view, self._offset)
        self._offset += _BUFFER
        self._fill = 0

    def _write_at(self, data: memoryview, offset: int) -> None:
        done = 0
        while done < len(data):
            try:
                n = os.pwritev(self._fd, [data[done:]], offset + done)
            except OSError as e:
                # A file system may take the open flag and refuse the writes (or a short
                # direct write may leave the rest unaligned): go on through the page cache.
                if e.errno != errno.EINVAL or not self.direct:
                    raise
                self._buffered()
                continue
            if n == 0:
                raise OSError(errno.EIO, "write wrote nothing")
            done += n
            if done < len(data) and self.direct:
                self._buffered()

    def _buffered(self) -> None:
        fcntl.fcntl(self._fd, fcntl.F_SETFL, fcntl.fcntl(self._fd, fcntl.F_GETFL) & ~_O_DIRECT)
        self.direct = False
