"""Fixtures of the client tests: a real server per module (from tests/server)."""

from __future__ import annotations

import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "server"))
from serverproc import ServerProcess


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ServerProcess]:
    s = ServerProcess(tmp_path_factory.mktemp("client") / "data", "--no-demo", "--cache", "256M")
    s.start()
    yield s
    s.stop()


@pytest.fixture(scope="module")
def url(server: ServerProcess) -> str:
    """The URL as `vastray serve` prints it, key included."""
    return f"{server.url}/?key={server.key}"
