"""Parts as the renderer and the server use them: a model's part of every input triangle
is a table of runs over input triangle ids (`docs/FORMAT.md`, the parts section), and
a highlight set of parts reaches the renderer as runs of triangle ids
(`RenderParams.highlight`), so the native code needs no part table of its own."""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any

import numpy as np

from vastray.modelfile import part_of

__all__ = ["PartTable", "highlight_ranges", "runs_from_ids"]


def runs_from_ids(triangle_ids: np.ndarray, part_ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The runs (first triangle id, part) of a mesh whose triangle `i` has input id
    `triangle_ids[i]` and part `part_ids[i]`; ids missing from the mesh (dropped as
    degenerate) join the run before them, which is harmless: no hit can name them."""
    order = np.argsort(triangle_ids, kind="stable")
    ids = np.asarray(triangle_ids, dtype=np.int64)[order]
    parts = np.asarray(part_ids, dtype=np.int64)[order]
    if ids.size == 0:
        return np.zeros(0, np.uint32), np.zeros(0, np.int32)
    starts = np.flatnonzero(np.r_[True, parts[1:] != parts[:-1]])
    firsts = ids[starts]
    firsts[0] = 0
    return firsts.astype(np.uint32), parts[starts].astype(np.int32)


def highlight_ranges(
    firsts: np.ndarray, parts: np.ndarray, input_triangles: int, selected: Iterable[int]
) -> np.ndarray:
    """Sorted, disjoint runs [first, end) of the input triangle ids whose part is in
    `selected`, as an (N, 2) int64 array for `RenderParams.highlight`; adjacent runs are
    merged, so a part given as many runs costs the renderer no more than it must."""
    chosen = np.fromiter((int(p) for p in selected), dtype=np.int64)
    if chosen.size == 0 or len(firsts) == 0:
        return np.zeros((0, 2), np.int64)
    firsts = np.asarray(firsts, dtype=np.int64)
    ends = np.r_[firsts[1:], np.int64(input_triangles)]
    keep = np.isin(np.asarray(parts, dtype=np.int64), chosen) & (ends > firsts)
    lo, hi = firsts[keep], ends[keep]
    if lo.size == 0:
        return np.zeros((0, 2), np.int64)
    # Runs are in id order; a run that starts where the previous kept one ends joins it.
    new = np.r_[True, lo[1:] != hi[:-1]]
    group = np.cumsum(new) - 1
    out = np.empty((int(group[-1]) + 1, 2), np.int64)
    out[:, 0] = lo[new]
    out[:, 1] = np.maximum.reduceat(hi, np.flatnonzero(new))
    return out


class PartTable:
    """A model's parts (`ModelFile.parts`) with the runs that give every input
    triangle's part: what an open model keeps (`OutOfCoreModel.part_table`) to name
    picks and highlight."""

    def __init__(
        self, parts: list[Any], firsts: np.ndarray, part_ids: np.ndarray, input_triangles: int
    ) -> None:
        self.parts = parts
        self.firsts = np.asarray(firsts, dtype=np.int64)
        self.part_ids = np.asarray(part_ids, dtype=np.int32)
        self.input_triangles = int(input_triangles)

    @classmethod
    def of_file(cls, model_file: Any) -> PartTable:
        """The table of an open `vastray.modelfile.ModelFile` (empty without parts)."""
        parts = list(model_file.parts)
        if not parts:
            return cls.empty()
        firsts, part_ids = model_file.part_runs
        return cls(parts, firsts, part_ids, int(model_file.header["input_triangles"]))

    @classmethod
    def empty(cls) -> PartTable:
        """A model without parts."""
        return cls([], np.zeros(0, np.int64), np.zeros(0, np.int32), 0)

    def __len__(self) -> int:
        return len(self.parts)

    def part_of(self, triangle_ids: np.ndarray) -> np.ndarray:
        """The part of each input triangle id (int32; -1 for none, and for ids < 0)."""
        return part_of(self.firsts, self.part_ids, triangle_ids, self.input_triangles)

    def name(self, part: int) -> str | None:
        return self.parts[part].name if 0 <= part < len(self.parts) else None

    def search(self, query: str = "") -> list[Any]:
        """The parts whose name contains `query`, ignoring case, in table order."""
        q = query.strip().casefold()
        return [p for p in self.parts if q in p.name.casefold()] if q else list(self.parts)

    def ranges(self, selected: Iterable[int]) -> np.ndarray:
        """`RenderParams.highlight` for a set of part ids (unknown ids are ignored)."""
        return highlight_ranges(self.firsts, self.part_ids, self.input_triangles, selected)
