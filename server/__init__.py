"""vastray.server: the render service (FastAPI on uvicorn).

`vastray serve` runs it; `create_app(Settings(...))` builds the ASGI app for other
servers and tests. See docs/API.md."""

from __future__ import annotations

from typing import TYPE_CHECKING

from vastray.server.settings import Settings

if TYPE_CHECKING:
    from fastapi import FastAPI

__all__ = ["Settings", "create_app", "serve"]


def create_app(settings: Settings | None = None) -> FastAPI:
    from vastray.server.app import create_app as make

    return make(settings)


def serve(settings: Settings) -> int:
    from vastray.server.main import serve as run

    return run(settings)
