"""The block cache under concurrency, checked by ThreadSanitizer.

Builds the native stress test (native/tests/cache_stress.cpp) with -fsanitize=thread
through CMake (the VASTRAY_TSAN option; the baseline ISA path's kernels only: the
threads around them are the same on every path) and runs it on two small built models: four
threads render orbiting views of both models in a cache of 24 slots, so blocks are
requested, fetched, published and evicted while other frames run. Any data race TSan
sees fails the run (exit status 66), as does a broken cache invariant.
`make tsan` runs the same thing by hand.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from vastray.build import build_model

REPO = Path(__file__).resolve().parents[1]


def _tool(name: str) -> str:
    # The test extra installs cmake and ninja into the environment running the tests.
    here = Path(sys.executable).parent / name
    found = str(here) if here.exists() else shutil.which(name)
    if found is None:
        pytest.fail(f"{name} is needed to build the TSan stress test (pip install '.[test]')")
    return found


@pytest.fixture(scope="module")
def stress_binary(tmp_path_factory: pytest.TempPathFactory) -> Path:
    build = tmp_path_factory.mktemp("tsan-build")
    configure = [
        _tool("cmake"), "-S", str(REPO), "-B", str(build), "-G", "Ninja",
        f"-DCMAKE_MAKE_PROGRAM={_tool('ninja')}", "-DCMAKE_BUILD_TYPE=RelWithDebInfo",
        "-DVASTRAY_PYTHON=OFF", "-DVASTRAY_NATIVE_TESTS=ON", "-DVASTRAY_TSAN=ON",
    ]  # fmt: skip
    for cmd in (configure, [_tool("cmake"), "--build", str(build), "--target", "cache_stress"]):
        result = subprocess.run(cmd, capture_output=True, text=True)
        assert result.returncode == 0, result.stdout + result.stderr
    return build / "native" / "cache_stress"


@pytest.fixture(scope="module")
def two_models(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    folder = tmp_path_factory.mktemp("tsan-models")
    a, b = folder / "plant.vast", folder / "spheres.vast"
    build_model("scene:plant:40000:2", a)
    build_model("scene:spheres:30000:3", b)
    return a, b


@pytest.mark.slow
def test_cache_stress_is_race_free_under_thread_sanitizer(
    stress_binary: Path, two_models: tuple[Path, Path]
) -> None:
    env = dict(os.environ, TSAN_OPTIONS="halt_on_error=1 exitcode=66 second_deadlock_stack=1")
    result = subprocess.run(
        [str(stress_binary), str(two_models[0]), str(two_models[1]), "40"],
        capture_output=True, text=True, env=env, timeout=600,
    )  # fmt: skip
    assert "ThreadSanitizer" not in result.stderr, result.stderr[-4000:]
    assert result.returncode == 0, result.stdout + result.stderr[-4000:]
    # The run did stress the cache: blocks were loaded and evicted while rendering.
    assert "evicted 0," not in result.stdout and "loaded 0," not in result.stdout, result.stdout
