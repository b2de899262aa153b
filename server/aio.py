"""Small asyncio helpers for long-lived responses that must end when the server stops."""

from __future__ import annotations

import asyncio
from typing import TypeVar

T = TypeVar("T")


class ShutdownError(Exception):
    """The server began shutting down while waiting."""


async def get_or_stop(queue: asyncio.Queue[T], stopping: asyncio.Event, timeout: float) -> T | None:
    """The next item of `queue`; None after `timeout` seconds of nothing; ShutdownError as soon
    as `stopping` is set."""
    if stopping.is_set():
        raise ShutdownError
    get = asyncio.ensure_future(queue.get())
    stop = asyncio.ensure_future(stopping.wait())
    try:
        done, _ = await asyncio.wait({get, stop}, timeout=timeout, return_when=asyncio.FIRST_COMPLETED)
    finally:
        for f in (get, stop):
            if not f.done():
                f.cancel()
    if get in done:
        return get.result()
    if stop in done:
        raise ShutdownError
    return None
