"""The blocking client, for scripts and notebooks: the asynchronous client run on an
event loop in a background thread (so it also works inside Jupyter, whose own loop is
already running in the main thread)."""

from __future__ import annotations

import asyncio
import functools
import threading
from collections.abc import Callable, Coroutine, Iterator
from typing import Any, TypeVar

from vastray.client.api import AsyncClient
from vastray.client.frames import Frame
from vastray.client.stream import AsyncView

T = TypeVar("T")


class _Portal:
    """An event loop in a daemon thread; `call` runs a coroutine there and waits."""

    def __init__(self) -> None:
        self.loop = asyncio.new_event_loop()
        self.thread = threading.Thread(target=self.loop.run_forever, name="vastray-client", daemon=True)
        self.thread.start()

    def call(self, coro: Coroutine[Any, Any, T], timeout: float | None = None) -> T:
        return asyncio.run_coroutine_threadsafe(coro, self.loop).result(timeout)

    def close(self) -> None:
        self.loop.call_soon_threadsafe(self.loop.stop)
        self.thread.join(5)


def _blocking(method: Callable[..., Coroutine[Any, Any, T]]) -> Callable[..., T]:
    """A blocking method that runs the asynchronous one of the same name."""

    @functools.wraps(method)
    def run(self: Any, *args: Any, **kw: Any) -> T:
        return self._portal.call(getattr(self._async, method.__name__)(*args, **kw))

    return run


def _attribute(name: str) -> Any:
    """A read-only property that reads the asynchronous view's attribute of that name."""
    return property(lambda self: getattr(self._async, name))


class View:
    """A live view, blocking (see AsyncView for what each method does)."""

    def __init__(self, portal: _Portal, view: AsyncView) -> None:
        self._portal = portal
        self._async = view

    def __enter__(self) -> View:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # What the live view knows, read as it is now (AsyncView documents each).
    camera = _attribute("camera")
    model_info = _attribute("model_info")
    events = _attribute("events")
    role = _attribute("role")
    following = _attribute("following")
    participant_id = _attribute("participant_id")
    participants = _attribute("participants")
    annotations = _attribute("annotations")
    saved_views = _attribute("saved_views")
    pointers = _attribute("pointers")

    set_camera = _blocking(AsyncView.set_camera)
    set_viewport = _blocking(AsyncView.set_viewport)
    set_quality = _blocking(AsyncView.set_quality)
    set_sections = _blocking(AsyncView.set_sections)
    set_section_box = _blocking(AsyncView.set_section_box)
    show = _blocking(AsyncView.show)
    set_highlight = _blocking(AsyncView.set_highlight)
    next_frame = _blocking(AsyncView.next_frame)
    final = _blocking(AsyncView.final)
    screenshot = _blocking(AsyncView.screenshot)
    pick = _blocking(AsyncView.pick)
    follow = _blocking(AsyncView.follow)
    annotate = _blocking(AsyncView.annotate)
    point = _blocking(AsyncView.point)
    save_view = _blocking(AsyncView.save_view)
    jump = _blocking(AsyncView.jump)
    handover = _blocking(AsyncView.handover)
    close = _blocking(AsyncView.close)

    def frames(self, timeout: float | None = 30.0) -> Iterator[Frame]:
        while True:
            yield self.next_frame(timeout)


class Client:
    """The render service from a script or a notebook.

    vr = Client("http://127.0.0.1:8000/?key=…")     # the URL `vastray serve` prints
    up = vr.upload("pump.ply")                        # built on the server
    vr.wait(up.created.job, progress=True)
    with vr.view(up.created.model.id, viewport=(1280, 720)) as view:
        view.set_camera(eye=(3, 2, 5), target=(0, 0, 0))
        view.final().save("pump.png")
    """

    def __init__(self, url: str | None = None, *, key: str | None = None, timeout: float = 120.0) -> None:
        self._portal = _Portal()
        self._async: AsyncClient = self._portal.call(_make(url, key, timeout))
        self.url = self._async.url
        self.key = self._async.key

    def __enter__(self) -> Client:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        self._portal.call(self._async.aclose())
        self._portal.close()

    health = _blocking(AsyncClient.health)
    models = _blocking(AsyncClient.models)
    model = _blocking(AsyncClient.model)
    parts = _blocking(AsyncClient.parts)
    upload = _blocking(AsyncClient.upload)
    register = _blocking(AsyncClient.register)
    update_model = _blocking(AsyncClient.update_model)
    delete = _blocking(AsyncClient.delete)
    token = _blocking(AsyncClient.token)
    start_review = _blocking(AsyncClient.start_review)
    review = _blocking(AsyncClient.review)
    model_views = _blocking(AsyncClient.model_views)
    save_model_view = _blocking(AsyncClient.save_model_view)
    delete_model_view = _blocking(AsyncClient.delete_model_view)
    build = _blocking(AsyncClient.build)
    job = _blocking(AsyncClient.job)
    jobs = _blocking(AsyncClient.jobs)
    cancel = _blocking(AsyncClient.cancel)
    wait = _blocking(AsyncClient.wait)
    render = _blocking(AsyncClient.render)
    pick = _blocking(AsyncClient.pick)

    def view(self, model: Any, **kw: Any) -> View:
        """A live view of a model (opened; close it, or use it in a `with`)."""
        view = self._async.view(model, **kw)
        self._portal.call(view.open())
        return View(self._portal, view)

    def join(self, review: str | None = None, **kw: Any) -> View:
        """A live view in a design review (opened): see AsyncClient.join."""
        view = self._portal.call(self._async.join(review, **kw))
        self._portal.call(view.open())
        return View(self._portal, view)


async def _make(url: str | None, key: str | None, timeout: float) -> AsyncClient:
    # httpx binds its connection pool to the loop it is first used on: make it there.
    return AsyncClient(url, key=key, timeout=timeout)
