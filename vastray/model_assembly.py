"""The write phase of a build: the model file assembled from the writer's blocks
(docs/FORMAT.md §3, §5 and "Building a model", step 5).

The native writer appends every block to the model file as it is made, past the page
cache, behind room kept in front for the header and the block index (`front_reserve`).
Assembling the file writes the header and the index there and moves the last blocks of
the file into what the index leaves of that room; nothing else is copied. Where the
room does not fit the index, or the model is smaller than the room or would leave more
than `front_slack` of it empty, the model is written again, every block in id order, as
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
_NO_BLOCKS = (np.zeros((0, 5), np.uint32), np.zeros(0, np.uint64))
# Zero bytes the front may keep between the last block moved there and the first block
# written behind it; a file written whole has none.
FRONT_SLACK = 64 << 10


def front_slack(blocks_bytes: int) -> int:
    """The zero bytes a model whose blocks take `blocks_bytes` may keep in front: at most
    1/256 of them (a page at least) and FRONT_SLACK. A small model that would keep more
    is written whole instead, which costs little at its size (64 KiB of zeros were up
    to 1 B/triangle of the 69,451-triangle bunny)."""
    return min(FRONT_SLACK, max(_ALIGN, blocks_bytes >> 8))


def front_reserve(triangles: int) -> int:
    """Bytes kept at the start of the model file for the header and the index of a model
    with a block per 256 triangles (built models have one per 1,000 or more,
    bench/results) and 64 tiers of 64 levels, rounded up to a 4 KiB page. The last
    blocks written fill what the index leaves."""
    entries = 64 * 64 + triangles // 256 + 4096
    need = modelfile.HEADER_SIZE + 24 * entries
    return -(-need // _ALIGN) * _ALIGN


@dataclass
class StreamLayout:
    """The model's blocks in block-id order: the level table's records (first, count,
    items, extra), the index entries (stored size, raw size, crc32, codec), and each
    block's offset in the file the writer appended it to (`at`)."""

    records: list[tuple[int, int, int, int]]
    entries: list[tuple[int, int, int, int]]
    at: np.ndarray  # (blocks,) int64
    tier_count: int  # 0: untiered (one record per level)

    @property
    def stored(self) -> np.ndarray:
        return np.fromiter((e[0] for e in self.entries), np.int64, len(self.entries))


def assemble_streams(stats: dict[str, Any], levels: dict[int, Any], tiered: bool) -> StreamLayout:
    """Lays the streams out level by level, and within a level coarsest tier first
    (docs/FORMAT.md §3, §5). `levels` (the writer's) holds per level its blocks'
    entries, tiers and offsets in the order they were finished, each tier's in its
    stream's order."""
    node_streams: list[list[tuple[int, int, int, int]]] = stats["node_streams"]
    triangle_streams: list[tuple[int, int, int, int]] = stats["triangle_streams"]
    tiers = max(len(t) for t in [*node_streams, triangle_streams]) if tiered else 1
    records: list[tuple[int, int, int, int]] = []
    entries: list[tuple[int, int, int, int]] = []
    ats: list[np.ndarray] = []
    for level, counts in [*enumerate(node_streams), (-1, triangle_streams)]:
        rows, offsets = levels.get(level, _NO_BLOCKS)
        rows = np.asarray(rows, dtype=np.int64).reshape(-1, 5)
        offsets = np.asarray(offsets, dtype=np.int64)
        for tier in range(tiers):
            mine = np.flatnonzero(rows[:, 4] == tier)
            blocks, _, items, extra = counts[tier] if tier < len(counts) else (0, 0, 0, 0)
            if len(mine) != blocks:
                raise RuntimeError(f"level {level} tier {tier}: {len(mine)} blocks written, {blocks} counted")
            records.append((len(entries), len(mine), items, extra))
            entries.extend(tuple(int(x) for x in rows[i, :4]) for i in mine)
            ats.append(offsets[mine])
    at = np.concatenate(ats) if ats else np.zeros(0, np.int64)
    return StreamLayout(records, entries, at, tiers if tiered else 0)


def write_model(
    partial: Path,
    fields: dict[str, Any],
    layout: StreamLayout,
    parts: modelfile.PartTable | None,
    output: tuple[str, int, int, bool],
    progress: Callable[[int, int], None],
) -> tuple[int, bool]:
    """Writes the model to `partial`, the file the writer appended the blocks to
    (`output`, the writer's: that path, where the blocks start and end), fsynced; returns
    its size and whether the blocks stayed where the writer put them (False: the file
    was written whole, blocks in id order). `progress(done, total)` counts the block
    bytes this phase copies."""
    if output[0] != str(partial):
        raise ValueError(f"the writer wrote {output[0]}, not {partial}")
    section = parts.pack() if parts is not None else b""
    part_count = len(parts.names) if parts is not None else 0
    size = _write_in_place(partial, fields, layout, section, part_count, output, progress)
    if size is not None:
        return size, True
    compact = partial.with_name(partial.name + ".compact")
    try:
        size = _write_whole(partial, compact, fields, layout, section, part_count, progress)
        os.replace(compact, partial)
    finally:
        compact.unlink(missing_ok=True)
    return size, False


def _write_whole(
    source: Path,
    target: Path,
    fields: dict[str, Any],
    layout: StreamLayout,
    section: bytes,
    part_count: int,
    progress: Callable[[int, int], None],
) -> int:
    """`target`, fsynced: the blocks of `source` one after the other in id order, with
    the header, the index and the parts section; returns its size."""
    with DirectFile(target) as out:
        return modelfile.write_model_file(
            out,
            fields,
            layout.records,
            layout.entries,
            _block_ranges(source, layout, progress),
            section,
            part_count,
            layout.tier_count,
        )


def _write_in_place(
    partial: Path,
    fields: dict[str, Any],
    layout: StreamLayout,
    section: bytes,
    part_count: int,
    output: tuple[str, int, int, bool],
    progress: Callable[[int, int], None],
) -> int | None:
    """The header, the index and the file's last blocks into the room in front of the
    blocks in `partial`, which is then cut behind what is left and ends in the parts
    section; None when the room cannot hold the index, would take every block, or would
    be left more than front_slack short."""
    _, front, end, _ = output
    n = len(layout.entries)
    data_offset = modelfile.HEADER_SIZE + 24 * (len(layout.records) + n)
    if data_offset > front:
        return None
    stored = layout.stored
    in_file_order = np.argsort(layout.at, kind="stable")
    # The longest run of the file's last blocks that fits the room (the writer appended
    # them one after the other, so they are one range of the file).
    behind = np.cumsum(stored[in_file_order][::-1])
    k = int(np.searchsorted(behind, front - data_offset, side="right"))
    if k == n or front - data_offset - (int(behind[k - 1]) if k else 0) > front_slack(int(behind[-1])):
        return None  # the model is smaller than the room, or leaves too much of it empty
    moving = in_file_order[n - k :]
    blocks_end = int(layout.at[moving[0]]) if k else end
    offsets = layout.at.copy()
    if k:
        offsets[moving] = data_offset + np.concatenate([[0], np.cumsum(stored[moving])[:-1]])
    header, index = modelfile.pack_head(
        fields,
        layout.records,
        layout.entries,
        offsets.tolist(),
        blocks_end,
        section,
        part_count,
        layout.tier_count,
    )
    total = end - blocks_end
    progress(0, total)
    head = bytearray(front)
    head[: len(header)] = header
    head[len(header) : data_offset] = index
    with open(partial, "rb") as f:
        moved = os.pread(f.fileno(), total, blocks_end)
    if len(moved) != total:
        raise RuntimeError(f"{partial}: shorter than the blocks written to it")
    head[data_offset : data_offset + total] = moved
    with DirectFile(partial, append_at=blocks_end) as out:
        out.write_at(0, head)
        out.write(section)
    progress(total, total)
    return blocks_end + len(section)


def _block_ranges(
    path: Path, layout: StreamLayout, progress: Callable[[int, int], None]
) -> Iterator[modelfile.FileRange]:
    """Every block's bytes in id order, as ranges of `path` (consecutive bytes read at
    once)."""
    stored = layout.stored
    total = int(stored.sum())
    runs: list[list[int]] = []
    for at, size in zip(layout.at.tolist(), stored.tolist(), strict=True):
        if runs and runs[-1][0] + runs[-1][1] == at:
            runs[-1][1] += size
        else:
            runs.append([at, size])
    fd = os.open(path, os.O_RDONLY)
    written = 0
    try:
        for at, size in runs:
            while size > 0:  # in pieces, for the progress bar
                piece = min(size, 64 << 20)
                yield modelfile.FileRange(fd, at, piece)
                at, size = at + piece, size - piece
                written += piece
                progress(written, total)
    finally:
        os.close(fd)


# The header fields a model's own header gives a copy of it (pack_head fills the rest).
_KEPT_FIELDS = (
    "flags", "centre", "cell_lo", "cell_hi", "triangle_count", "input_triangles", "degenerate",
    "basic_nodes", "lod_nodes", "leaves", "voxels_one", "voxels_six", "voxels_packed", "references", "up",
)  # fmt: skip


def rewrite_in_id_order(source: Path, target: Path) -> int:
    """Writes a copy of the model `source` to `target` with its blocks one after the
    other in id order, the layout every model had before blocks were written in place
    (the same header fields, index entries and block bytes; only the offsets differ).
    Returns the copy's size. For comparing the layouts (bench/layout.py)."""
    with modelfile.ModelFile(source) as model:
        h = model.header
        tiers = h["tier_count"] if h["flags"] & modelfile.FLAG_TIERED else 0
        records = [(s.first, s.count, s.items, s.extra) for s in model.streams]
        entries = [(b.stored_size, b.raw_size, b.crc32, b.codec) for b in model.blocks]
        at = np.fromiter((b.offset for b in model.blocks), np.int64, len(model.blocks))
    with open(source, "rb") as f:
        section = os.pread(f.fileno(), h["parts_size"], h["parts_offset"]) if h["parts_size"] else b""
    fields = {k: h[k] for k in _KEPT_FIELDS}
    layout = StreamLayout(records, entries, at, tiers)
    return _write_whole(source, target, fields, layout, section, h["part_count"], lambda done, total: None)
