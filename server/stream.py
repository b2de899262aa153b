"""Frame streaming over WebSockets (docs/PROTOCOL.md): one connection per viewer.

A `Connection` reads the client's messages (validated, rate-limited, each bad one
answered with an error event while the connection lives on), keeps at most
`MAX_IN_FLIGHT` frames unacknowledged, sends only the newest frame it has (a slow
client gets fewer frames, never a queue of stale ones), and sends heartbeats. A client
that vanished without a close is reaped by the WebSocket pings (uvicorn) or by its own
silence; its view stops rendering at once. Sessions outlive connections for a while,
so a client that reconnects resumes its camera and quality.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import secrets
import time
from collections import deque
from dataclasses import dataclass
from typing import Any

import numpy as np
from fastapi import APIRouter, WebSocket
from pydantic import ValidationError
from starlette.websockets import WebSocketDisconnect, WebSocketState

from vastray.protocol import (
    FLAG_COMPLETE,
    FLAG_FINAL,
    FLAG_SCREENSHOT,
    FORMAT_JPEG,
    FORMAT_PNG,
    PROTOCOL_VERSION,
    CameraMessage,
    CameraState,
    ErrorEvent,
    FrameHeader,
    Hello,
    PickMessage,
    QualityMessage,
    SectionPlane,
    StatsEvent,
    StreamQuality,
    Viewport,
    ViewportMessage,
    Welcome,
    parse_client_message,
)
from vastray.schemas import PartInfo, describe_errors
from vastray.server.errors import ApiError
from vastray.server.reviews import REVIEW_MESSAGES, Participant, ReviewSession
from vastray.server.views import RenderedFrame, View, camera_of, camera_problem, default_camera

log = logging.getLogger("vastray.stream")
router = APIRouter(tags=["stream"])

MAX_IN_FLIGHT = 2  # frames sent and not yet acknowledged
WELCOME_PARTS = 20_000  # parts listed in a welcome (all of them in GET .../parts)
AUTO_ACCURACY_AFTER = 1.0  # seconds a view stays still and finished before it is measured
# Messages that change what a view shows: in a review, only its driver's count.
DRIVING = ("camera", "viewport", "quality", "sections", "highlight")
HELLO_TIMEOUT = 10.0
HEARTBEAT_SECONDS = 15.0  # an event at least this often, so proxies keep the socket
SESSION_TTL = 600.0  # how long a disconnected session can be resumed
MESSAGE_RATE = 240.0  # messages a second a client may send, on average
MESSAGE_BURST = 480.0
FLOOD_SECONDS = 5.0  # over the rate this long without pause: the connection is closed

# Close codes (4000-4999 are the application's own).
CLOSE_GOING_AWAY = 1001
CLOSE_POLICY = 1008
CLOSE_BAD_HELLO = 4400
CLOSE_UNAUTHORIZED = 4401
CLOSE_FORBIDDEN = 4403
CLOSE_NOT_FOUND = 4404
CLOSE_TIMEOUT = 4408


@dataclass
class Session:
    id: str
    model_id: str
    camera: CameraState
    viewport: Viewport
    quality: StreamQuality
    expires: float
    sections: list[SectionPlane]
    highlight: list[int]


class StreamHub:
    """The server's streaming state: views, connections, sessions, the scheduler."""

    def __init__(self, state: Any) -> None:
        from vastray.server.scheduler import Scheduler

        self.state = state
        self.sessions: dict[str, Session] = {}
        self.connections: set[Connection] = set()
        self.reviews: dict[str, ReviewSession] = {}
        self.scheduler = Scheduler(
            state.store.cache, state.renders.executor, state.settings.render_workers, self.deliver
        )

    def deliver(self, view: View, frame: RenderedFrame | None, warning: str | None) -> None:
        """A frame rendered and encoded once, offered to every subscriber of the view."""
        if frame is not None:
            self.state.metrics.frame_rendered("stream", frame.stats, frame.encode_ms / 1000)
        for sub in list(view.subscribers):
            assert isinstance(sub, Connection)
            if warning is not None:
                sub.event(ErrorEvent(code="render_warning", message=warning).model_dump())
            if frame is not None:
                sub.offer(frame)

    def announce(self, model_id: str, message: dict[str, Any]) -> None:
        """An event for every connection viewing a model (on the event loop's thread)."""
        for conn in list(self.connections):
            if conn.view is not None and conn.view.model_id == model_id:
                conn.event(message)

    def remember(self, session_id: str, view: View) -> None:
        """Keeps a closed connection's view settings for a reconnect to resume."""
        now = time.time()
        self.sessions = {k: s for k, s in self.sessions.items() if s.expires > now}
        self.sessions[session_id] = Session(
            session_id,
            view.model_id,
            view.camera,
            view.viewport,
            view.quality,
            now + SESSION_TTL,
            list(view.sections),
            list(view.highlight),
        )

    async def close_all(self, reason: str) -> None:
        await asyncio.gather(
            *(c.close(CLOSE_GOING_AWAY, reason) for c in list(self.connections)), return_exceptions=True
        )


class _Bucket:
    """A token bucket of the messages a client may send, and how long it has been over."""

    def __init__(self, rate: float, burst: float) -> None:
        self.rate, self.burst = rate, burst
        self.tokens = burst
        self.at = time.monotonic()
        self.over_since: float | None = None  # the first drop of the current run of drops
        self.last_drop = 0.0

    def take(self) -> bool:
        now = time.monotonic()
        self.tokens = min(self.burst, self.tokens + (now - self.at) * self.rate)
        self.at = now
        if self.over_since is not None and now - self.last_drop > 1.0:
            self.over_since = None  # a second without drops: back within the rate
        if self.tokens >= 1.0:
            self.tokens -= 1.0
            return True
        self.last_drop = now
        if self.over_since is None:
            self.over_since = now
        return False

    def flooding(self) -> bool:
        return self.over_since is not None and time.monotonic() - self.over_since > FLOOD_SECONDS


class Connection:
    """One viewer's WebSocket; a subscriber of its view."""

    def __init__(self, hub: StreamHub, ws: WebSocket) -> None:
        self.hub = hub
        self.ws = ws
        self.state = hub.state
        self.session_id = f"ses-{secrets.token_hex(8)}"
        self.view: View | None = None  # the view this connection shows (maybe a review's shared one)
        self.viewport = Viewport()
        self.review: ReviewSession | None = None
        self.participant: Participant | None = None
        self.grant: Any = None
        self.model_id: str | None = None
        self.frame_number = 0
        self.latest: RenderedFrame | None = None
        self.unacked: deque[int] = deque()
        self.events: deque[dict[str, Any]] = deque()
        self.wake = asyncio.Event()
        self.closed = False
        self.bucket = _Bucket(MESSAGE_RATE, MESSAGE_BURST)
        self.sent_times: deque[float] = deque(maxlen=32)
        self.last_sent_seq = -1
        self.pending_screenshots: list[str] = []
        self.last_received = time.monotonic()
        self.tasks: set[asyncio.Task[None]] = set()

    def _spawn(self, coro: Any) -> None:
        # Keep a reference: the loop holds tasks only weakly.
        task = asyncio.create_task(coro)
        self.tasks.add(task)
        task.add_done_callback(self.tasks.discard)

    # -- the view's subscriber side --------------------------------------------------------

    def can_take(self) -> bool:
        return not self.closed and self.latest is None and len(self.unacked) < MAX_IN_FLIGHT

    def offer(self, frame: RenderedFrame) -> None:
        if self.closed:
            return
        self.latest = frame  # latest wins: an unsent older frame is dropped
        self.wake.set()

    def event(self, message: dict[str, Any]) -> None:
        if not self.closed:
            self.events.append(message)
            self.wake.set()

    # -- the connection's life -------------------------------------------------------------

    async def run(self) -> None:
        await self.ws.accept()
        self.hub.connections.add(self)
        self.state.viewers += 1
        sender = asyncio.create_task(self._sender(), name=f"{self.session_id}-sender")
        try:
            hello = await self._hello()
            if hello is None:
                return
            await self._open_view(hello)
            if self.view is None:
                return
            await self._receive()
        except WebSocketDisconnect:
            pass
        finally:
            self.closed = True
            sender.cancel()
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await sender
            await self._leave()
            self.hub.connections.discard(self)
            self.state.viewers -= 1

    async def _leave(self) -> None:
        view = self.view
        if view is not None and (self.review is None or view is not self.review.shared):
            self.hub.remember(self.session_id, view)
        self._unsubscribe()
        if self.review is not None and self.participant is not None:
            review = self.review
            await review.leave(self.participant)
            if not review.participants and review.shared is not None:
                shared, review.shared = review.shared, None
                self._drop(shared)
        self.hub.scheduler.notify()

    def _subscribe(self, view: View) -> None:
        self._unsubscribe()
        view.subscribers.add(self)
        self.view = view
        self.latest = None
        self.last_sent_seq = -1  # another view: its own camera sequence
        if view.phase == "idle" and view.last_final is not None:
            # A still, finished view renders nothing more: a subscriber that joins it (a
            # review's follower, one going back to following) gets its last frame.
            self.offer(view.last_final)
        self.hub.scheduler.notify()

    def _unsubscribe(self) -> None:
        view, self.view = self.view, None
        if view is None:
            return
        view.subscribers.discard(self)
        shared = self.review is not None and view is self.review.shared
        if not view.subscribers and not shared:
            self._drop(view)

    def _drop(self, view: View) -> None:
        # The lease ends when no frame of the view renders any more: releasing the last
        # one closes a model that is being deleted, and a frame still tracing it would
        # read freed memory (the server died so, a viewer leaving a deleted model).
        model_id = view.model_id
        self.hub.scheduler.remove(view, then=lambda: self.state.store.release(model_id))

    def _new_view(
        self,
        view_id: str,
        camera: CameraState,
        viewport: Viewport,
        quality: StreamQuality,
        sections: list[Any] | None = None,
        highlight: list[int] | None = None,
    ) -> View:
        """A view of this connection's model, with its own lease on the model."""
        assert self.model_id is not None
        model = self.state.store.acquire(self.model_id)
        view = View(
            view_id,
            self.model_id,
            model,
            camera,
            viewport,
            quality,
            render_threads=self.state.settings.render_threads,
            parts=model.part_table,
        )
        view.sections = list(sections or [])
        view.highlight = list(highlight or [])
        self.hub.scheduler.add(view)
        return view

    def follow(self, shared: View | None) -> None:
        """Review participants: show the shared view (follow), or a view of one's own
        that starts where the shared one is (None)."""
        if shared is not None:
            self._subscribe(shared)
            return
        current = self.view
        assert current is not None
        own = self._new_view(
            self.session_id,
            current.camera,
            self.viewport,
            current.quality,
            current.sections,
            current.highlight,
        )
        self._subscribe(own)

    async def close(self, code: int, reason: str) -> None:
        if self.ws.client_state == WebSocketState.CONNECTED:
            with contextlib.suppress(Exception):
                await self.ws.send_text(json.dumps({"type": "closing", "code": code, "reason": reason}))
                await self.ws.close(code, reason[:120])
        self.closed = True

    async def _fail(self, code: int, error: str, message: str) -> None:
        with contextlib.suppress(Exception):
            await self.ws.send_text(
                json.dumps(ErrorEvent(code=error, message=message, fatal=True).model_dump())
            )
        await self.close(code, message)

    # -- hello -----------------------------------------------------------------------------

    async def _hello(self) -> Hello | None:
        try:
            text = await asyncio.wait_for(self.ws.receive_text(), HELLO_TIMEOUT)
        except TimeoutError:
            await self._fail(CLOSE_TIMEOUT, "no_hello", f"send a hello message within {HELLO_TIMEOUT:g} s")
            return None
        except KeyError:  # a binary message (receive_text found no text)
            await self._fail(CLOSE_BAD_HELLO, "bad_hello", "the first message must be a JSON hello")
            return None
        try:
            raw = json.loads(text)
            hello = Hello.model_validate(raw)
        except ValueError as exc:
            detail = describe_errors(exc.errors()) if isinstance(exc, ValidationError) else str(exc)
            await self._fail(CLOSE_BAD_HELLO, "bad_hello", f"hello: {detail}")
            return None
        if hello.protocol != PROTOCOL_VERSION:
            await self._fail(
                CLOSE_BAD_HELLO,
                "protocol_version",
                f"this server speaks protocol {PROTOCOL_VERSION}, the client {hello.protocol}",
            )
            return None
        credential = hello.token or self.ws.query_params.get("token") or self.ws.query_params.get("key")
        try:
            grant = await asyncio.to_thread(self.state.auth.grant, credential)
        except ApiError as exc:
            await self._fail(CLOSE_UNAUTHORIZED, exc.code, exc.message)
            return None
        problem = await asyncio.to_thread(self._access_problem, grant, hello)
        if problem is not None:
            await self._fail(*problem)
            return None
        self.grant = grant
        return hello

    def _access_problem(self, grant: Any, hello: Hello) -> tuple[int, str, str] | None:
        """Why this credential may not open this hello's view (None: it may). A review
        token grants its review, and through it the review's model."""
        if hello.review is None:
            if grant.may_view_model(hello.model):
                return None
            return CLOSE_FORBIDDEN, "forbidden", f"this token does not grant access to model {hello.model}"
        if not (grant.admin or (grant.scope == "review" and grant.subject == hello.review)):
            return CLOSE_FORBIDDEN, "forbidden", f"this token does not grant access to review {hello.review}"
        review = self.state.registry.review(hello.review)
        if review is None:
            return CLOSE_NOT_FOUND, "review_not_found", f"no review {hello.review!r}"
        if review["model_id"] != hello.model:
            return (
                CLOSE_FORBIDDEN,
                "forbidden",
                f"review {hello.review} is of model {review['model_id']}, not {hello.model}",
            )
        return None

    async def _open_view(self, hello: Hello) -> None:
        store = self.state.store
        row = await asyncio.to_thread(self.state.registry.model, hello.model)
        if row is None or row.state == "deleting":
            await self._fail(CLOSE_NOT_FOUND, "model_not_found", f"no model {hello.model!r}")
            return
        if row.state == "building":
            if not await self._wait_for_build(row.job_id):
                return
        try:
            # Opening reads the model's header, index and coarsest levels: off the loop. The
            # connection holds this lease while it sets up; its views take their own.
            model = await asyncio.to_thread(store.acquire, hello.model)
        except ApiError as exc:
            await self._fail(CLOSE_NOT_FOUND, exc.code, exc.message)
            return
        try:
            await self._welcome(hello, model)
        finally:
            store.release(hello.model)

    async def _welcome(self, hello: Hello, model: Any) -> None:
        self.model_id = hello.model
        session = self.hub.sessions.pop(hello.session, None) if hello.session else None
        resumed = session is not None and session.model_id == hello.model
        viewport = hello.viewport or (session.viewport if resumed and session else Viewport())
        problem = self._viewport_problem(viewport)
        if problem:
            await self._fail(CLOSE_BAD_HELLO, "viewport_too_large", problem)
            return
        # A camera no frame can be rendered from is refused here, as a camera message is,
        # rather than failing every render of the view.
        problem = camera_problem(hello.camera) if hello.camera is not None else None
        if problem:
            await self._fail(CLOSE_BAD_HELLO, "bad_camera", f"hello: {problem}")
            return
        self.viewport = viewport
        # Everything the welcome needs from disk comes first: once this connection
        # subscribes to a view, its sender may send that view's frame, and no frame may
        # go out before the welcome.
        row = await asyncio.to_thread(self.state.store.row, hello.model)
        info = self.state.store.info(row).model_dump()
        # The page's parts panel searches these itself; a bigger table is searched over
        # GET /api/models/{id}/parts.
        info["parts"] = [PartInfo.of(p).model_dump() for p in model.part_table.parts[:WELCOME_PARTS]]
        if resumed and session is not None:
            self.session_id = session.id
            camera, quality = session.camera, session.quality
            sections, highlight = session.sections, session.highlight
        else:
            sections, highlight = [], []
            camera = hello.camera or default_camera(model, viewport, row.up)
            quality = hello.quality or StreamQuality()
        review_info = None
        if hello.review is not None:
            stored = await asyncio.to_thread(self.state.registry.review, hello.review)
            review = self.hub.reviews.get(hello.review)
            if review is None:  # (looked up again: another participant may have made it meanwhile)
                review = ReviewSession(self.hub, stored)
                self.hub.reviews[hello.review] = review
            presenter = bool(self.grant.admin or self.grant.role == "presenter")
            self.review = review
            self.participant = review.join(self, hello.name, presenter)
            if review.shared is None:
                review.shared = self._new_view(
                    review.id,
                    review.initial_camera() or camera,
                    viewport,
                    review.initial_quality() or quality,
                    [SectionPlane(**p) for p in review.saved_state.get("sections", [])],
                    review.saved_state.get("highlight", []),
                )
            elif self.participant.role == "presenter":
                review.shared.set_viewport(viewport)  # frames fit the presenter's screen
            self._subscribe(review.shared)
            review_info = review.welcome(self.participant)
        else:
            self._subscribe(self._new_view(self.session_id, camera, viewport, quality, sections, highlight))
        view = self.view
        assert view is not None
        limits = {
            "max_pixels": self.state.settings.max_pixels,
            "max_in_flight": MAX_IN_FLIGHT,
            "message_rate": MESSAGE_RATE,
            "max_message_bytes": self.state.settings.max_message_bytes,
        }
        welcome = Welcome(
            session=self.session_id,
            resumed=resumed,
            model=info,
            camera=view.camera,
            viewport=view.viewport,
            quality=view.quality,
            sections=view.sections,
            highlight=view.highlight,
            limits=limits,
            review=review_info,
        )
        self.event(welcome.model_dump())
        if self.review is not None and self.participant is not None:
            await self.review.send_state(self.participant)

    async def _wait_for_build(self, job_id: str | None) -> bool:
        """Streams the build's progress until the model is ready (True) or the build
        ended otherwise (False, the client told why)."""
        jobs = self.state.jobs
        if job_id is None:
            return True
        queue = jobs.listen(job_id)
        try:
            info = jobs.info(job_id)
            while True:
                self.event({"type": "job", **info.model_dump()})
                if info.state == "succeeded":
                    return True
                if info.state in ("failed", "cancelled", "interrupted"):
                    await self._fail(
                        CLOSE_NOT_FOUND, "build_failed", f"the model's build {info.state}: {info.error}"
                    )
                    return False
                from vastray.server.aio import get_or_stop

                got = await get_or_stop(queue, self.state.stopping, HEARTBEAT_SECONDS)
                info = got if got is not None else jobs.info(job_id)
        finally:
            jobs.unlisten(queue, job_id)

    def _viewport_problem(self, viewport: Viewport) -> str | None:
        pixels = viewport.width * viewport.height
        if pixels > self.state.settings.max_pixels:
            return (
                f"a {viewport.width}x{viewport.height} viewport is {pixels:,} pixels; "
                f"the server's pixel budget is {self.state.settings.max_pixels:,}"
            )
        return None

    # -- receiving -------------------------------------------------------------------------

    async def _receive(self) -> None:
        timeout = self.state.settings.client_timeout
        while not self.closed:
            try:
                message = await asyncio.wait_for(self.ws.receive(), timeout)
            except TimeoutError:
                log.info("session %s: nothing heard for %.0f s: closing", self.session_id, timeout)
                await self.close(CLOSE_TIMEOUT, f"nothing heard from the client for {timeout:g} s")
                return
            if message["type"] == "websocket.disconnect":
                return
            self.last_received = time.monotonic()
            if not self.bucket.take():
                if self.bucket.flooding():
                    await self._fail(CLOSE_POLICY, "flooding", "too many messages for too long; closing")
                    return
                self._error(
                    "rate_limited", f"more than {MESSAGE_RATE:g} messages a second; this one was dropped"
                )
                continue
            text = message.get("text")
            if text is None:
                self._error("bad_message", "messages are JSON text; binary messages are not understood")
                continue
            if len(text) > self.state.settings.max_message_bytes:
                self._error(
                    "message_too_large",
                    f"messages are limited to {self.state.settings.max_message_bytes} bytes",
                )
                continue
            try:
                msg = parse_client_message(text)
            except ValueError as exc:
                self._error("bad_message", str(exc))
                continue
            await self._handle(msg)

    def _error(self, code: str, message: str) -> None:
        self.event(ErrorEvent(code=code, message=message).model_dump())

    async def _handle(self, msg: Any) -> None:
        view = self.view
        assert view is not None
        scheduler = self.hub.scheduler
        kind = msg.type
        if kind in REVIEW_MESSAGES:
            if self.review is None or self.participant is None:
                self._error("not_in_review", f"{kind}: this connection is not in a review")
                return
            await self.review.handle(self.participant, msg)
            scheduler.notify()
            return
        if kind in DRIVING and self.participant is not None and self.review is not None:
            if kind == "viewport":
                self.viewport = Viewport(**msg.model_dump(exclude={"type"}))
            if not self.review.may_drive(self.participant):
                if kind != "viewport":
                    self._error("following", f"{kind}: you follow the presenter; stop following to navigate")
                return
        if kind == "camera":
            assert isinstance(msg, CameraMessage)
            problem = camera_problem(msg)
            if problem:
                self._error("bad_camera", problem)
                return
            if msg.seq < view.camera.seq:
                return  # an older camera than one already applied: latest wins
            view.set_camera(CameraState(**msg.model_dump(exclude={"type"})))
        elif kind == "viewport":
            assert isinstance(msg, ViewportMessage)
            viewport = Viewport(**msg.model_dump(exclude={"type"}))
            problem = self._viewport_problem(viewport)
            if problem:
                self._error("viewport_too_large", problem)
                return
            self.viewport = viewport
            view.set_viewport(viewport)
        elif kind == "quality":
            assert isinstance(msg, QualityMessage)
            changes = {k: v for k, v in msg.model_dump(exclude={"type"}).items() if v is not None}
            try:
                quality = StreamQuality(**{**view.quality.model_dump(), **changes})
            except (ValidationError, ValueError) as exc:
                detail = describe_errors(exc.errors()) if isinstance(exc, ValidationError) else str(exc)
                self._error("bad_quality", f"quality: {detail}")
                return
            view.set_quality(quality)
        elif kind == "ack":
            while self.unacked and self.unacked[0] <= msg.frame:
                self.unacked.popleft()
            self.wake.set()
        elif kind == "ping":
            self.event({"type": "pong", "t": msg.t, "server_time": time.time()})
        elif kind == "screenshot":
            self.pending_screenshots.append(msg.id)
            if view.phase == "idle" and view.last_final is not None:
                self._spawn(self._screenshot(view.last_final))
        elif kind == "pick":
            self._spawn(self._pick(msg))
        elif kind == "sections":
            view.set_sections(msg.planes)
            if self.review is not None and view is self.review.shared:
                self.review.broadcast({"type": "sections", "planes": [p.model_dump() for p in msg.planes]})
        elif kind == "highlight":
            view.set_highlight(msg.parts)
        elif kind == "accuracy":
            self._spawn(self._accuracy(view))
        elif kind == "bye":
            await self.close(1000, "bye")
            return
        scheduler.notify()

    async def _pick(self, msg: PickMessage) -> None:
        view = self.view
        if view is None:
            return
        c = msg.camera or view.camera
        width, height = msg.width or view.viewport.width, msg.height or view.viewport.height
        camera = camera_of(c, width, height)
        renders = self.state.renders

        def run() -> Any:
            points = np.asarray(msg.points, dtype=np.float64)
            origins, directions = camera.image_rays(points, view.model.bounds)
            return renders.pick_rays(view.model, origins, directions, 5.0, view.sections, parts=view.parts)

        try:
            result = await asyncio.get_running_loop().run_in_executor(renders.executor, run)
        except Exception as exc:
            self._error("pick_failed", f"pick: {exc}")
            return
        self.event({"type": "pick_result", "id": msg.id, **result.model_dump()})

    async def _auto_accuracy(self, view: View, version: int) -> None:
        await asyncio.sleep(AUTO_ACCURACY_AFTER)
        if view.version == version and view.phase == "idle" and self.view is view:
            await self._accuracy(view)

    async def _accuracy(self, view: View) -> None:
        loop = asyncio.get_running_loop()
        try:
            result = await loop.run_in_executor(self.state.renders.executor, view.measure_accuracy)
        except Exception as exc:
            self._error("accuracy_failed", f"accuracy: {exc}")
            return
        self.event(result)

    async def _screenshot(self, frame: RenderedFrame) -> None:
        if not self.pending_screenshots or frame.image is None:
            return
        ids, self.pending_screenshots = self.pending_screenshots, []
        from vastray.server.encoders import encode

        loop = asyncio.get_running_loop()
        png = await loop.run_in_executor(self.state.renders.executor, encode, frame.image, "png")
        for shot_id in ids:
            await self._send_frame(frame, png, FORMAT_PNG, frame.flags | FLAG_SCREENSHOT)
            self.event({"type": "screenshot", "id": shot_id, "frame": self.frame_number})

    # -- sending ---------------------------------------------------------------------------

    async def _sender(self) -> None:
        while True:
            try:
                await asyncio.wait_for(self.wake.wait(), HEARTBEAT_SECONDS)
            except TimeoutError:
                self.events.append({"type": "heartbeat", "server_time": time.time()})
            self.wake.clear()
            if self.state.stopping.is_set():
                await self.close(CLOSE_GOING_AWAY, "the server is shutting down")
                return
            while self.events:
                await self.ws.send_text(json.dumps(self.events.popleft()))
            frame = self.latest
            if frame is not None and len(self.unacked) < MAX_IN_FLIGHT:
                self.latest = None
                if frame.job.seq < self.last_sent_seq:
                    continue  # never a frame older than one already sent
                await self._send_frame(frame, frame.data, FORMAT_JPEG, frame.flags)
                if frame.flags & FLAG_FINAL and self.pending_screenshots:
                    self._spawn(self._screenshot(frame))
                view = self.view
                if frame.flags & FLAG_FINAL and view is not None and view.quality.auto_accuracy:
                    self._spawn(self._auto_accuracy(view, view.version))
                self.hub.scheduler.notify()  # this connection can take another frame

    async def _send_frame(self, frame: RenderedFrame, data: bytes, fmt: int, flags: int) -> None:
        self.frame_number += 1
        n = self.frame_number
        job = frame.job
        now = time.time()
        header = FrameHeader(
            n,
            job.seq,
            frame.width,
            frame.height,
            fmt,
            flags,
            job.pass_number,
            frame.render_ms,
            frame.encode_ms,
            job.params.pixels_of_error,
            job.scale,
            1000 * now,
        )
        await self.ws.send_bytes(header.pack() + data)
        self.unacked.append(n)
        self.last_sent_seq = max(self.last_sent_seq, job.seq)
        mono = time.monotonic()
        self.sent_times.append(mono)
        latency = mono - job.camera_at
        metrics = self.state.metrics
        if not flags & FLAG_SCREENSHOT and (job.moving or job.pass_number == 1):
            metrics.latency.observe(latency)
        metrics.frames_sent.labels("stream").inc()
        metrics.bytes_sent.labels("stream").inc(len(data))
        s = frame.stats
        fps = (
            (len(self.sent_times) - 1) / (self.sent_times[-1] - self.sent_times[0])
            if len(self.sent_times) > 1
            else 0.0
        )
        stats = StatsEvent(
            frame=n,
            camera_seq=job.seq,
            camera=job.camera_state,
            pass_number=job.pass_number,
            moving=job.moving,
            complete=bool(flags & FLAG_COMPLETE),
            final=bool(flags & FLAG_FINAL),
            width=frame.width,
            height=frame.height,
            scale=job.scale,
            pixels_of_error=job.params.pixels_of_error,
            render_ms=frame.render_ms,
            encode_ms=frame.encode_ms,
            queue_ms=1000 * (frame.started_at - job.camera_at),
            latency_ms=1000 * latency,
            bytes=len(data),
            fps=fps,
            working_set_bytes=s.working_set_bytes,
            pending_blocks=s.pending,
            cache_hit_rate=s.cache_hit_rate,
            voxel_hits=s.voxel_hits,
            rays=s.rays,
        )
        await self.ws.send_text(stats.model_dump_json())


@router.websocket("/api/stream")
async def stream(ws: WebSocket) -> None:
    hub: StreamHub = ws.app.state.vastray.streams
    await Connection(hub, ws).run()
