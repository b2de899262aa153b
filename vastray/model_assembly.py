"""The write phase of a build: the model file assembled from the writer's levels
(docs/FORMAT.md §3, §5 and "Building a model", step 5).

The native writer appends each node level's blocks to a scratch file of its own. A
large build's triangle level, most of the model's bytes, goes straight into the model
file instead, past the page cache, from an offset that leaves room in front for the
header, the block index and as many node blocks as fit (`front_reserve`). Assembling
that file writes the front and appends the other node blocks and the parts section
behind the triangle level: the triangle blocks are not copied. Where the front does not
fit the index, or would be left more than `FRONT_SLACK` short (a small model has too
few node bytes to fill it), the model is written again, every block in id order, as
every model was before.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from vastray import modelfile
from vastray.direct_io import DirectFile

_ALIGN = 4096
# Zero bytes the front may keep between its last node block and the triangle level;
# a compacted file has none.
FRONT_SLACK = 64 << 10


def front_reserve(triangles: int) -> int:
    """Bytes kept at the start of the model file, before the triangle level: room for
    the header and the index of a model with a block per 256 triangles (built models
    have one per 1,000 or more, bench/results) and 64 tiers of 64 levels, rounded up to
    a 4 KiB page. Node blocks fill what the index leaves."""
    entries = 64 * 64 + triangles // 256 + 4096
    need = modelfile.HEADER_SIZE + 24 * entries
    return -(-need // _ALIGN) * _ALIGN


@dataclass
class StreamLayout:
    """Where every block of the model comes from, in block-id order: the level table's
    records (first, count, items, extra), the index entries (stored size, raw size,
    crc32, codec), and per block the file holding its bytes (`paths[source]`) and their
    offset there (`at`)."""

    records: list[tuple[int, int, int, int]]
    entries: list[tuple[int, int, int, int]]
    paths: list[str]
    source: np.ndarray  # (blocks,) int: index into paths
    at: np.ndarray  # (blocks,) int64
    tier_count: int  # 0: untiered (one record per level)
    triangles: int  # index into paths of the triangle level's file

    @property
    def stored(self) -> np.ndarray:
        return np.fromiter((e[0] for e in self.entries), np.int64, len(self.entries))


def assemble_streams(
    stats: dict[str, Any],
    level_files: dict[int, Any],
    tiered: bool,
    triangle_output: tuple[str, int, int, bool] | None = None,
) -> StreamLayout:
    """Lays the streams out level by level, and within a level coarsest tier first
    (docs/FORMAT.md §3, §5). A level file holds its tiers' blocks in the order they were
    finished, each tier's in its stream's order. `triangle_output` (the writer's): the
    triangle level's blocks lie in the model file from its start offset."""
    node_streams: list[list[tuple[int, int, int, int]]] = stats["node_streams"]
    triangle_streams: list[tuple[int, int, int, int]] = stats["triangle_streams"]
    tiers = max(len(t) for t in [*node_streams, triangle_streams]) if tiered else 1
    records: list[tuple[int, int, int, int]] = []
    entries: list[tuple[int, int, int, int]] = []
    paths: list[str] = []
    sources: list[np.ndarray] = []
    ats: list[np.ndarray] = []
    triangles = -1
    for level, counts in [*enumerate(node_streams), (-1, triangle_streams)]:
        path, rows = level_files.get(level, ("", np.zeros((0, 5), np.uint32)))
        rows = np.asarray(rows, dtype=np.int64).reshape(-1, 5)
        base = triangle_output[1] if level < 0 and triangle_output is not None else 0
        offsets = base + np.concatenate([[0], np.cumsum(rows[:, 0])])
        if level < 0:
            triangles = len(paths)
        paths.append(path)
        for tier in range(tiers):
            mine = np.flatnonzero(rows[:, 4] == tier)
            blocks, _, items, extra = counts[tier] if tier < len(counts) else (0, 0, 0, 0)
            if len(mine) != blocks:
                raise RuntimeError(f"level {level} tier {tier}: {len(mine)} blocks written, {blocks} counted")
            records.append((len(entries), len(mine), items, extra))
            entries.extend(tuple(int(x) for x in rows[i, :4]) for i in mine)
            sources.append(np.full(len(mine), len(paths) - 1, np.int64))
            ats.append(offsets[mine])
    if triangle_output is not None:
        _, start, end, _ = triangle_output
        rows = np.asarray(level_files.get(-1, ("", np.zeros((0, 5), np.uint32)))[1], np.int64).reshape(-1, 5)
        if start + int(rows[:, 0].sum()) != end:
            raise RuntimeError(
                f"{triangle_output[0]}: the triangle level's blocks do not end where it does ({end})"
            )
    return StreamLayout(
        records,
        entries,
        paths,
        np.concatenate(sources) if sources else np.zeros(0, np.int64),
        np.concatenate(ats) if ats else np.zeros(0, np.int64),
        tiers if tiered else 0,
        triangles,
    )


def write_model(
    partial: Path,
    fields: dict[str, Any],
    layout: StreamLayout,
    parts: modelfile.PartTable | None,
    triangle_output: tuple[str, int, int, bool] | None,
    progress: Callable[[int, int], None],
) -> tuple[int, bool]:
    """Writes the model to `partial` (fsynced); returns its size and whether the
    triangle level stayed where the writer put it (False: the file was written whole,
    blocks in id order). `progress(done, total)` counts the block bytes this phase
    copies: all of them, or those of the node levels."""
    if triangle_output is not None:
        size = _write_around_triangles(partial, fields, layout, parts, triangle_output, progress)
        if size is not None:
            return size, True
    compact = partial.with_name(partial.name + ".compact")
    try:
        with DirectFile(compact) as out:
            size = modelfile.write_model_file(
                out,
                fields,
                layout.records,
                layout.entries,
                _block_ranges(layout, progress),
                parts,
                layout.tier_count,
            )
        os.replace(compact, partial)
    finally:
        compact.unlink(missing_ok=True)
    return size, False


def _write_around_triangles(
    partial: Path,
    fields: dict[str, Any],
    layout: StreamLayout,
    parts: modelfile.PartTable | None,
    triangle_output: tuple[str, int, int, bool],
    progress: Callable[[int, int], None],
) -> int | None:
    """The front (header, index, the first node blocks that fit) and the tail (the other
    node blocks, the parts section) around the triangle level in `partial`; None when
    the front cannot hold the index or would be left more than FRONT_SLACK short."""
    _, front, end, _ = triangle_output
    n = len(layout.entries)
    data_offset = modelfile.HEADER_SIZE + 24 * (len(layout.records) + n)
    if data_offset > front:
        return None
    stored = layout.stored
    offsets = layout.at.copy()  # the triangle blocks stay where they are
    nodes = np.flatnonzero(layout.source != layout.triangles)
    in_front: list[int] = []
    behind: list[int] = []
    pos = data_offset
    for i in nodes.tolist():  # first fit, in id order: the coarse levels come first
        if pos + stored[i] <= front:
            offsets[i] = pos
            pos += int(stored[i])
            in_front.append(i)
        else:
            behind.append(i)
    if front - pos > FRONT_SLACK:
        return None
    tail = end
    for i in behind:
        offsets[i] = tail
        tail += int(stored[i])
    section = parts.pack() if parts is not None else b""
    header, index = modelfile.pack_head(
        fields,
        layout.records,
        layout.entries,
        offsets.tolist(),
        tail,
        section,
        len(parts.names) if parts is not None else 0,
        layout.tier_count,
    )
    total = int(stored[nodes].sum())  # the block bytes this phase copies
    head = bytearray(front)
    head[: len(header)] = header
    head[len(header) : data_offset] = index
    fds = {s: os.open(layout.paths[s], os.O_RDONLY) for s in set(layout.source[nodes].tolist())}
    try:
        for i in in_front:
            data = os.pread(fds[int(layout.source[i])], int(stored[i]), int(layout.at[i]))
            if len(data) != stored[i]:
                raise RuntimeError(
                    f"{layout.paths[int(layout.source[i])]}: shorter than the blocks written to it"
                )
            head[offsets[i] : offsets[i] + len(data)] = data
        with DirectFile(partial, append_at=end) as out:
            out.write_at(0, head)
            written = int(stored[in_front].sum())
            progress(written, total)
            for s, at, size in _runs(behind, layout, stored):
                out.copy(fds[s], at, size)
                written += size
                progress(written, total)
            out.write(section)
            if out.size != tail + len(section):
                raise RuntimeError(
                    f"{partial}: wrote {out.size} bytes but the index describes {tail + len(section)}"
                )
    finally:
        for fd in fds.values():
            os.close(fd)
    progress(total, total)
    return tail + len(section)


def _runs(ids: list[int], layout: StreamLayout, stored: np.ndarray) -> Iterator[tuple[int, int, int]]:
    """(source, offset, size) of the blocks `ids`, in their order, consecutive bytes of
    one file read at once."""
    run: list[int] | None = None
    for i in ids:
        s, at, size = int(layout.source[i]), int(layout.at[i]), int(stored[i])
        if run is not None and run[0] == s and run[1] + run[2] == at:
            run[2] += size
            continue
        if run is not None:
            yield run[0], run[1], run[2]
        run = [s, at, size]
    if run is not None:
        yield run[0], run[1], run[2]


def _block_ranges(
    layout: StreamLayout, progress: Callable[[int, int], None]
) -> Iterator[modelfile.FileRange]:
    """Every block's bytes in id order, as ranges of the files holding them."""
    stored = layout.stored
    total = int(stored.sum())
    fds = {s: os.open(p, os.O_RDONLY) for s, p in enumerate(layout.paths) if p}
    written = 0
    try:
        for s, at, size in _runs(list(range(len(layout.entries))), layout, stored):
            while size > 0:  # in pieces, for the progress bar
                piece = min(size, 64 << 20)
                yield modelfile.FileRange(fds[s], at, piece)
                at, size = at + piece, size - piece
                written += piece
                progress(written, total)
    finally:
        for fd in fds.values():
            os.close(fd)
