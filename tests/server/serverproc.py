"""Helpers of the server tests: a real `vastray serve` (vastray.server.process) with a
fixed test key, and waiting for build jobs."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import httpx

from vastray.server import process
from vastray.server.process import URL_LINE, VASTRAY

__all__ = ["KEY", "URL_LINE", "VASTRAY", "ServerProcess", "wait_for_job"]

KEY = "test-key-0123456789abcdef"


class ServerProcess(process.ServerProcess):
    def __init__(self, data_dir: Path, *args: str, key: str | None = KEY, **kw: Any) -> None:
        super().__init__(data_dir, *args, key=key, **kw)


def wait_for_job(
    client: httpx.Client,
    job_id: str,
    timeout: float = 180.0,
    states: tuple[str, ...] = ("succeeded", "failed", "cancelled", "interrupted"),
) -> dict[str, Any]:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        job = client.get(f"/api/jobs/{job_id}").json()
        if job["state"] in states:
            return job
        time.sleep(0.1)
    raise AssertionError(f"job {job_id} not in {states} after {timeout} s: {job}")
