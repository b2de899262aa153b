"""Helpers of the server tests: a real `vastray serve` (vastray.server.process) with a
fixed test key, waiting for build jobs, and reading an error answer."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import httpx

from vastray.server import process
from vastray.server.process import URL_LINE, VASTRAY

__all__ = ["KEY", "URL_LINE", "VASTRAY", "ServerProcess", "error", "wait_for_job"]

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


def error(r: httpx.Response, status: int, code: str | None = None) -> str:
    """The message of an error answer (docs/API.md's form), after checking its status and,
    if given, its code."""
    assert r.status_code == status, (r.status_code, r.text)
    body = r.json()["error"]
    if code is not None:
        assert body["code"] == code, body
    assert body["message"]
    return str(body["message"])
