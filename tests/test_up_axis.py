"""Which way is up in a model file: `vastray build --up` writes it into the header (bytes
236-247, a unit vector), `inspect` shows it, `render` frames the model upright by it
(the picture of the y-up original, turned); a file built without it has those bytes
zero, as every earlier file, and reads as not said; a damaged one is refused."""

from __future__ import annotations

import json
import struct
import zlib
from pathlib import Path

import numpy as np
import pytest
import trimesh
from modelwalk import WalkError, read_up
from PIL import Image
from test_build import SMALL_MEMORY, header_offset, run_cli

from vastray import scenes
from vastray.build import BuildOptions, build_model
from vastray.modelfile import HEADER_SIZE, ModelError, ModelFile

Y_TO_Z = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])  # +y to +z


@pytest.fixture(scope="module")
def meshes(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """The plant as generated (y-up) and turned a quarter about x (z-up)."""
    folder = tmp_path_factory.mktemp("up")
    upright = folder / "plant.ply"
    scenes.write_scene("plant", 20_000, 2, upright)
    turned = trimesh.load(upright, process=False)
    turned.vertices = np.asarray(turned.vertices) @ Y_TO_Z.T
    turned.export(folder / "plant-z.ply")
    return upright, folder / "plant-z.ply"


def image(path: Path) -> np.ndarray:
    return np.asarray(Image.open(path).convert("RGB")).astype(int)


def differing(a: np.ndarray, b: np.ndarray) -> float:
    return float((np.abs(a - b).sum(axis=2) > 30).mean())


def test_build_writes_up_and_render_frames_by_it(meshes: tuple[Path, Path], tmp_path: Path) -> None:
    upright, turned = meshes
    memory = f"{SMALL_MEMORY >> 20}M"
    out = run_cli("build", str(turned), "-o", "z.vast", "--up", "0,0,2", "--memory", memory, cwd=tmp_path)
    assert out.returncode == 0, out.stderr
    out = run_cli("build", str(upright), "-o", "y.vast", "--memory", memory, cwd=tmp_path)
    assert out.returncode == 0, out.stderr
    with ModelFile(tmp_path / "z.vast") as z, ModelFile(tmp_path / "y.vast") as y:
        assert z.up == (0.0, 0.0, 1.0) and y.up is None
    assert read_up(tmp_path / "z.vast") == (0.0, 0.0, 1.0) and read_up(tmp_path / "y.vast") is None
    # Not said: the bytes stay the zero padding every earlier writer left there.
    at = header_offset("up")
    assert (tmp_path / "y.vast").read_bytes()[at:HEADER_SIZE] == bytes(HEADER_SIZE - at)
    stats = json.loads(run_cli("inspect", "z.vast", "--json", cwd=tmp_path).stdout)
    assert stats["up"] == [0.0, 0.0, 1.0]
    assert "up         0,0,1" in run_cli("inspect", "z.vast", cwd=tmp_path).stdout
    assert "not said" in run_cli("inspect", "y.vast", cwd=tmp_path).stdout

    # Rendered without --up, the z-up model is framed about its up: the y-up original's
    # picture (but for the odd pixel where the two trees split a tie differently).
    for model, args in (("z", ()), ("y", ()), ("side", ("--up", "0,1,0"))):
        source = "y.vast" if model == "y" else "z.vast"
        out = run_cli("render", source, "-o", f"{model}.png", "--size", "240x160", *args, cwd=tmp_path)
        assert out.returncode == 0, out.stderr
    said = run_cli("render", "z.vast", "-o", "again.png", "--size", "24x16", cwd=tmp_path).stdout
    assert "--up 0,0,1" in said  # the camera it printed, to repeat it
    original = image(tmp_path / "y.png")
    assert differing(image(tmp_path / "z.png"), original) < 0.01
    assert differing(image(tmp_path / "side.png"), original) > 0.2  # --up wins


def test_bad_ups_are_refused(meshes: tuple[Path, Path], tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="up must be a finite, non-zero 3-vector"):
        BuildOptions(up=(0.0, 0.0, 0.0)).check()
    out = run_cli("build", str(meshes[0]), "-o", "x.vast", "--up", "0,1", cwd=tmp_path)
    assert out.returncode == 2 and "expected three comma-separated numbers" in out.stderr
    assert not (tmp_path / "x.vast").exists()

    path = tmp_path / "z.vast"
    build_model(str(meshes[1]), path, BuildOptions(memory=SMALL_MEMORY, up=(0.0, 0.0, 1.0)))
    for bad in [(0.0, 0.0, 2.0), (float("nan"), 0.0, 1.0)]:
        data = bytearray(path.read_bytes())
        struct.pack_into("<3f", data, header_offset("up"), *bad)
        crc_at = header_offset("header_crc32")
        struct.pack_into("<I", data, crc_at, 0)
        struct.pack_into("<I", data, crc_at, zlib.crc32(bytes(data[:HEADER_SIZE])))
        damaged = tmp_path / "damaged.vast"
        damaged.write_bytes(bytes(data))
        with pytest.raises(ModelError, match="implausible up vector"):
            ModelFile(damaged)
        with pytest.raises(WalkError, match="neither zero nor a unit vector"):
            read_up(damaged)


def printed_camera(stdout: str) -> tuple[np.ndarray, np.ndarray]:
    """(unit vector from the target to the eye, up) of the camera `render` printed."""
    line = next(x for x in stdout.splitlines() if x.startswith("camera "))
    words = line.split()
    vec = {w: np.array(words[i + 1].split(","), float) for i, w in enumerate(words) if w[:2] == "--"}
    d = vec["--eye"] - vec["--target"]
    return d / np.linalg.norm(d), vec["--up"]


def test_render_takes_a_standard_view(meshes: tuple[Path, Path], tmp_path: Path) -> None:
    """`render --view` frames the whole model from a side, upright about the model's up:
    the z-up model's front is -y, its top +z with +y up the screen (the page's views)."""
    build_model(str(meshes[1]), tmp_path / "z.vast", BuildOptions(memory=SMALL_MEMORY, up=(0.0, 0.0, 1.0)))
    for view, side, up in [
        ("front", [0, -1, 0], [0, 0, 1]),
        ("right", [1, 0, 0], [0, 0, 1]),
        ("top", [0, 0, 1], [0, 1, 0]),
        ("bottom", [0, 0, -1], [0, -1, 0]),
    ]:
        args = ("--view", view, "-o", f"{view}.png", "--size", "96x64")
        out = run_cli("render", "z.vast", *args, cwd=tmp_path)
        assert out.returncode == 0, out.stderr
        direction, screen_up = printed_camera(out.stdout)
        np.testing.assert_allclose(direction, side, atol=1e-6, err_msg=view)
        np.testing.assert_allclose(screen_up, up, atol=1e-6, err_msg=view)
        assert image(tmp_path / f"{view}.png").std() > 5, f"the {view} view is blank"
    out = run_cli("render", "z.vast", "--view", "front", "--eye", "1,2,3", "-o", "x.png", cwd=tmp_path)
    assert out.returncode == 2 and "standard view frames the whole model" in out.stderr
    assert not (tmp_path / "x.png").exists()
