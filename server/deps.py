"""What route handlers ask for: the server's state and the caller's grant."""

from __future__ import annotations

from typing import Annotated

from fastapi import Depends, Request

from vastray.server.app import State
from vastray.server.auth import Grant


def state_of(request: Request) -> State:
    return request.app.state.vastray  # type: ignore[no-any-return]


def admin(request: Request) -> Grant:
    """The caller holds an API key (write endpoints)."""
    return state_of(request).auth.require_key(request)


# A route parameter `_: Admin` makes the route need an API key.
Admin = Annotated[Grant, Depends(admin)]
