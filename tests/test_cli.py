"""The `vastray` command line end to end, as a user runs it (a real subprocess)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from vastray.ingest import load_mesh


def run_cli(*args: str, cwd: Path, env: dict[str, str] | None = None) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "vastray", *args],
        cwd=cwd,
        capture_output=True,
        text=True,
        timeout=300,
        env=None if env is None else {**os.environ, **env},
    )


@pytest.fixture(scope="module")
def spheres_ply(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("cli") / "spheres.ply"
    result = run_cli("scene", "spheres", "--triangles", "5000", "--seed", "3", "-o", str(out), cwd=out.parent)
    assert result.returncode == 0, result.stderr
    assert "wrote" in result.stdout
    return out


def test_scene_command_writes_a_loadable_model(spheres_ply: Path) -> None:
    mesh = load_mesh(spheres_ply)
    assert abs(mesh.triangle_count - 5000) <= 250
    assert mesh.face_colours is not None


def test_render_auto_framed_model_fills_the_image(spheres_ply: Path, tmp_path: Path) -> None:
    png = tmp_path / "out.png"
    result = run_cli("render", str(spheres_ply), "--size", "160x120", "-o", str(png), cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    image = np.asarray(Image.open(png))
    assert image.shape == (120, 160, 3)
    # The stats line reports the frame's ray count: one primary ray per pixel.
    assert f"{160 * 120:,} rays" in result.stdout
    # Auto-framing puts the model in view: a good share of pixels differ from the
    # background gradient (whose columns are all equal within a row).
    differs_from_row = np.any(image != image[:, :1, :], axis=2)
    assert differs_from_row.mean() > 0.2


def test_render_with_explicit_camera_and_every_shading(spheres_ply: Path, tmp_path: Path) -> None:
    means = {}
    for shading in ("normal", "headlight", "sun", "ao"):
        png = tmp_path / f"{shading}.png"
        result = run_cli(
            "render",
            str(spheres_ply),
            "--eye",
            "0,30,60",
            "--target",
            "0,0,0",
            "--up",
            "0,1,0",
            "--fov",
            "50",
            "--size",
            "96x64",
            "--shading",
            shading,
            "--ao-samples",
            "4",
            "-o",
            str(png),
            cwd=tmp_path,
        )
        assert result.returncode == 0, result.stderr
        assert "--eye 0,30,60 --target 0,0,0" in result.stdout
        # Every mode's primary rays walk the wide BVH: it is built (and reported) before the frame.
        assert "wide BVH   8-wide BVH in" in result.stdout, result.stdout
        means[shading] = np.asarray(Image.open(png), dtype=np.float64).mean()
    # Different shading modes give different pictures of the same view.
    assert len({round(m, 3) for m in means.values()}) == 4


@pytest.mark.parametrize(
    ("env", "shading", "wide", "kd"),
    [
        ({}, "sun", True, False),
        ({"VASTRAY_PRIMARY": "kd"}, "headlight", False, True),
        ({"VASTRAY_PRIMARY": "kd"}, "sun", True, True),
        ({"VASTRAY_ANYHIT": "kd"}, "ao", True, True),
    ],
)
def test_render_builds_only_what_its_rays_walk(
    spheres_ply: Path, tmp_path: Path, env: dict[str, str], shading: str, wide: bool, kd: bool
) -> None:
    """An in-core scene's structures are built on first use: the CLI builds and reports
    the ones the frame's rays walk before the frame, and no other."""
    png = tmp_path / "frame.png"
    result = run_cli(
        "render",
        str(spheres_ply),
        "--size",
        "64x48",
        "--shading",
        shading,
        "-o",
        str(png),
        cwd=tmp_path,
        env=env,
    )
    assert result.returncode == 0, result.stderr
    assert ("wide BVH   8-wide BVH in" in result.stdout) == wide, result.stdout
    assert ("kd-tree    kd-tree in" in result.stdout) == kd, result.stdout


def test_render_builtin_scene_spec(tmp_path: Path) -> None:
    png = tmp_path / "mb.png"
    result = run_cli("render", "scene:mandelbulb:3000:2", "--size", "64x48", "-o", str(png), cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    assert png.exists()


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["render", "missing.obj", "-o", "x.png"], "missing.obj: no such file"),
        (["render", "scene:spheres:2000:1", "--size", "0x10", "-o", "x.png"], "image size"),
        (["render", "scene:spheres:2000:1", "--eye", "1,2", "-o", "x.png"], "three comma-separated"),
        (["render", "scene:spheres:2000:1", "--eye", "nan,0,0", "-o", "x.png"], "non-finite"),
        (["render", "scene:spheres:2000:1", "--fov", "180", "-o", "x.png"], "fov"),
        (["render", "scene:spheres:2000:1", "--fov", "0", "-o", "x.png"], "fov must be between"),
        (
            ["render", "scene:spheres:2000:1", "--eye", "0,0,0", "--target", "0,0,0", "-o", "x.png"],
            "coincide",
        ),
        (["render", "scene:nosuch:2000:1", "-o", "x.png"], "nosuch"),
        (["scene", "plant", "--triangles", "2000", "-o", "x.xyz"], "x.xyz"),
    ],
)
def test_bad_input_gives_a_clear_error_and_writes_nothing(
    args: list[str], message: str, tmp_path: Path
) -> None:
    result = run_cli(*args, cwd=tmp_path)
    assert result.returncode == 2
    assert message in result.stderr
    assert "Traceback" not in result.stderr
    assert list(tmp_path.iterdir()) == []


def test_nan_vertex_file_is_rejected_by_name(tmp_path: Path) -> None:
    bad = tmp_path / "bad.obj"
    bad.write_text("v 0 0 0\nv 1 0 0\nv 0 nan 0\nf 1 2 3\n")
    result = run_cli("render", str(bad), "-o", str(tmp_path / "x.png"), cwd=tmp_path)
    assert result.returncode == 2
    assert "bad.obj" in result.stderr and "vertex" in result.stderr
    assert not (tmp_path / "x.png").exists()
