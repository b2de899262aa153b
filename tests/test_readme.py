"""The README's example of the Python core (in-core rendering, batch queries, building
a model, reading it back, out-of-core rendering) runs as written."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest
from readme import block_using


def test_the_core_example_runs_as_written(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(tmp_path)  # it writes plant.vast in the working folder
    names: dict[str, object] = {}
    exec(compile(block_using("vastray.render"), "README.md", "exec"), names)

    assert (tmp_path / "plant.vast").is_file() and os.path.getsize(tmp_path / "plant.vast") > 0
    assert names["report"] is not None
    raw = names["raw"]
    assert isinstance(raw, (bytes, bytearray, memoryview)) and len(raw) > 0
    hits = names["hits"]
    assert np.count_nonzero(np.asarray(hits["prim"]) >= 0) > 0  # the mandelbulb is in view
    shadowed = np.asarray(names["shadowed"])
    assert shadowed.dtype == bool and 0 < shadowed.mean() < 1  # some of its hits lie in shadow
    frame, exact = names["frame"], names["exact"]
    assert frame.image.shape == (720, 1280, 3)  # the out-of-core overview
    assert exact.complete and exact.image.shape == (720, 1280, 3)
    assert np.count_nonzero(exact.prim >= 0) > 0  # full detail hits triangles
