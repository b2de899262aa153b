"""The README's example of the Python client runs as written against a real server:
upload, build with a progress bar, render, a streamed camera path, the final frame, a
pick, parts and a highlight, a lossless screenshot, a section box."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from vastray import scenes

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
from readme import block_using


def test_the_client_example_runs_as_written(
    url: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.chdir(tmp_path)  # it uploads pump.ply and saves its frames here
    scenes.write_scene("plant", 20_000, 5, tmp_path / "pump.ply")
    code = block_using("vastray.client")
    placeholder = 'Client("http://127.0.0.1:8000/?key=…")'
    assert placeholder in code
    names: dict[str, object] = {}
    exec(compile(code.replace(placeholder, f"Client({url!r})"), "README.md", "exec"), names)

    assert names["job"].state == "succeeded"
    assert names["frame"].image.shape == (720, 1280, 3)
    path = sorted(tmp_path.glob("path-*.jpg"))
    # While the camera moves the server may lower the resolution (docs/PROTOCOL.md): any
    # size up to the viewport's, at its aspect.
    sizes = [Image.open(p).size for p in path]
    assert len(path) == 30 and all(0 < w <= 1280 and abs(w * 720 - h * 1280) <= 1280 for w, h in sizes), sizes
    still = np.asarray(Image.open(tmp_path / "still.png").convert("RGB"))
    assert still.shape == (720, 1280, 3) and still.std() > 0  # the model, not a blank frame
    valves = np.asarray(Image.open(tmp_path / "valves.png").convert("RGB")).astype(int)
    boxed = np.asarray(Image.open(tmp_path / "boxed.png").convert("RGB")).astype(int)
    assert boxed.shape == valves.shape and np.abs(boxed - valves).mean() > 1  # the box cut something away
