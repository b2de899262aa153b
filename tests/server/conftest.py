"""Fixtures of the server tests: `server` is one real `vastray serve` per module over a
fresh data directory (tests that restart or kill a server start their own), `api` an
httpx client of it holding the API key."""

from __future__ import annotations

from collections.abc import Iterator

import httpx
import pytest
from serverproc import ServerProcess


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ServerProcess]:
    s = ServerProcess(tmp_path_factory.mktemp("srv") / "data", "--no-demo", "--cache", "256M")
    s.start()
    yield s
    s.stop()


@pytest.fixture(scope="module")
def api(server: ServerProcess) -> Iterator[httpx.Client]:
    with server.client() as c:
        yield c
