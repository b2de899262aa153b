"""The server's settings that depend on the machine: frames in flight follow the CPU set
the process may use (a container's or taskset's), and the environment still decides."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest
from pydantic import ValidationError

from vastray.server.settings import Settings, usable_cores


def settings_in_child(cores: set[int], env: dict[str, str] | None = None) -> str:
    """Settings().render_workers and usable_cores() as a process pinned to `cores` sees them."""
    code = (
        "import os\n"
        f"os.sched_setaffinity(0, {sorted(cores)!r})\n"
        "from vastray.server.settings import Settings, usable_cores\n"
        "print(Settings().render_workers, usable_cores())\n"
    )
    environ = {**os.environ, **(env or {})}
    run = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, env=environ, check=True
    )

    return run.stdout.strip()


@pytest.mark.skipif(not hasattr(os, "sched_setaffinity"), reason="needs Linux CPU affinity")
def test_one_core_still_keeps_two_frames_in_flight() -> None:
    cpu = min(os.sched_getaffinity(0))
    assert settings_in_child({cpu}) == "2 1"


@pytest.mark.skipif(not hasattr(os, "sched_setaffinity"), reason="needs Linux CPU affinity")
def test_the_environment_overrides_the_cores() -> None:
    cpu = min(os.sched_getaffinity(0))
    assert settings_in_child({cpu}, {"VASTRAY_RENDER_WORKERS": "5"}) == "5 1"


def test_default_follows_the_usable_cores(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("VASTRAY_RENDER_WORKERS", raising=False)
    assert Settings().render_workers == max(2, usable_cores() // 2)
    assert 1 <= usable_cores() <= (os.cpu_count() or 1)


def test_zero_workers_is_refused(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("VASTRAY_RENDER_WORKERS", "0")
    with pytest.raises(ValidationError, match="render_workers"):
        Settings()
