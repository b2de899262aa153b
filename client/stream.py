"""A live view of a model: the streaming protocol's client side (docs/PROTOCOL.md), on
the `websockets` library.

    async with client.view(model_id, viewport=(1280, 720)) as view:
        await view.set_camera(eye=(30, 20, 30), target=(0, 5, 0))
        frame = await view.final()          # refined, complete: the view is now idle
        frame.save("view.png")

Frames are acknowledged as the caller takes them, so a caller that reads slowly gets
fewer frames, never a backlog. The connection pings the server, and reconnects with
backoff after a network failure, resuming its session (camera, viewport, quality).
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import time
from collections.abc import AsyncIterator, Callable, Sequence
from typing import Any

import websockets
from websockets.exceptions import ConnectionClosed, InvalidStatus

from vastray.client.api import Plane, VastrayError, section_planes
from vastray.client.frames import Frame, decode_frame
from vastray.protocol import FLAG_SCREENSHOT, PROTOCOL_VERSION, CameraState, StreamQuality, Viewport
from vastray.schemas import PickHit, SectionPlane, section_box

log = logging.getLogger("vastray.client")

PING_SECONDS = 15.0
RECONNECT_DELAYS = (0.2, 0.5, 1.0, 2.0, 5.0)
FATAL_CLOSE = {4400, 4401, 4403, 4404}  # bad hello, unauthorized, forbidden, no such model


class AsyncView:
    def __init__(
        self,
        url: str,
        model: str,
        *,
        key: str | None = None,
        viewport: tuple[int, int] = (960, 540),
        camera: dict[str, Any] | None = None,
        quality: dict[str, Any] | None = None,
        reconnect: bool = True,
        on_event: Callable[[dict[str, Any]], None] | None = None,
        review: str | None = None,
        name: str | None = None,
    ) -> None:
        self.ws_url = url.replace("https://", "wss://").replace("http://", "ws://") + "/api/stream"
        self.model = model
        self.key = key
        self.viewport = Viewport(width=viewport[0], height=viewport[1])
        self.camera: CameraState | None = CameraState(**camera) if camera else None
        self.quality: StreamQuality | None = StreamQuality(**quality) if quality else None
        self.reconnect = reconnect
        self.on_event = on_event
        self.review = review  # the design review this view joined, or None
        self.name = name
        self.role: str | None = None  # in a review: "presenter" or "follower"
        self.participant_id: str | None = None  # in a review: this view's id in `participants`
        self._follows = False  # in a review: shows the shared view (as the server says)
        self.participants: list[dict[str, Any]] = []
        self.annotations: list[dict[str, Any]] = []
        self.saved_views: list[dict[str, Any]] = []  # in a review: its saved views, newest last
        self.pointers: dict[str, dict[str, Any]] = {}  # in a review: participant id -> pointer
        self.session: str | None = None
        self.welcome: dict[str, Any] = {}
        self.model_info: dict[str, Any] = {}
        self.events: list[dict[str, Any]] = []  # errors and notices, newest last (bounded)
        self.connects = 0
        self._ws: Any = None
        self._frames: asyncio.Queue[Frame] = asyncio.Queue()
        self._pending: dict[int, Frame] = {}  # frames waiting for their stats event
        self._picks: dict[str, asyncio.Future[list[PickHit]]] = {}
        self._shots: dict[str, asyncio.Future[Frame]] = {}
        self._shot_frames: dict[int, Frame] = {}
        self._seq = 0
        self._tasks: list[asyncio.Task[Any]] = []
        self._closed = False
        self._connected = asyncio.Event()
        self._failure: BaseException | None = None
        self._counter = 0

    # -- lifecycle -------------------------------------------------------------------------

    async def __aenter__(self) -> AsyncView:
        await self.open()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()

    async def open(self, timeout: float = 60.0) -> AsyncView:
        await asyncio.wait_for(self._connect(), timeout)
        self._tasks = [
            asyncio.create_task(self._run(), name="vastray-view"),
            asyncio.create_task(self._ping(), name="vastray-ping"),
        ]
        return self

    async def close(self) -> None:
        self._closed = True
        with contextlib.suppress(Exception):
            if self._ws is not None:
                await self._ws.send(json.dumps({"type": "bye"}))
                await self._ws.close()
        for t in self._tasks:
            t.cancel()
        for t in self._tasks:
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await t

    async def _connect(self) -> None:
        self._ws = await websockets.connect(self.ws_url, max_size=64 << 20, ping_interval=PING_SECONDS)
        hello: dict[str, Any] = {
            "type": "hello",
            "protocol": PROTOCOL_VERSION,
            "model": self.model,
            "token": self.key,
            "session": self.session,
            "viewport": self.viewport.model_dump(),
        }
        if self.review is not None:
            hello.update(review=self.review, name=self.name)
        # A review's shared view is the presenter's to set: a participant joins it as it is.
        if self.camera is not None and self.review is None:
            hello["camera"] = self.camera.model_dump()
        if self.quality is not None and self.review is None:
            hello["quality"] = self.quality.model_dump()
        await self._ws.send(json.dumps(hello))
        while True:  # job events come first while the model is still being built
            message = json.loads(await self._ws.recv())
            if message["type"] == "welcome":
                break
            if message["type"] == "error" and message.get("fatal"):
                raise VastrayError(0, message["code"], message["message"])
            self._note(message)
        self.welcome = message
        self.session = message["session"]
        self.model_info = message["model"]
        self.camera = CameraState(**message["camera"])
        self._seq = max(self._seq, self.camera.seq)
        self.quality = StreamQuality(**message["quality"])
        if message.get("review"):
            self.role = message["review"]["role"]
            self.participant_id = message["review"]["participant"]
            self._follows = bool(message["review"]["following"])
        self.connects += 1
        self._connected.set()

    async def _run(self) -> None:
        delays = iter(RECONNECT_DELAYS)
        while not self._closed:
            try:
                await self._read()
            except ConnectionClosed as exc:
                code = exc.rcvd.code if exc.rcvd is not None else None
                if self._closed:
                    return
                if code in FATAL_CLOSE or not self.reconnect:
                    self._failure = VastrayError(
                        0, f"closed_{code}", exc.rcvd.reason if exc.rcvd else str(exc)
                    )
                    self._wake_all()
                    return
            except (OSError, InvalidStatus) as exc:
                if not self.reconnect:
                    self._failure = exc
                    self._wake_all()
                    return
            self._connected.clear()
            # Reconnect with backoff; the session resumes the camera and quality.
            while not self._closed:
                await asyncio.sleep(next(delays, RECONNECT_DELAYS[-1]))
                try:
                    await self._connect()
                    delays = iter(RECONNECT_DELAYS)
                    break
                except (OSError, InvalidStatus, ConnectionClosed, VastrayError) as exc:
                    log.info("reconnect failed: %s", exc)

    async def _read(self) -> None:
        async for message in self._ws:
            if isinstance(message, bytes):
                frame = decode_frame(message, time.time())
                assert frame.header is not None
                if frame.header.flags & FLAG_SCREENSHOT:
                    self._shot_frames[frame.header.frame] = frame
                    await self._ack(frame.header.frame)
                else:
                    self._pending[frame.header.frame] = frame
                continue
            event = json.loads(message)
            kind = event.get("type")
            if kind == "stats":
                frame = self._pending.pop(event["frame"], None)
                if frame is not None:
                    frame.stats = event
                    camera = CameraState(**event["camera"])
                    # Where the server moved this view (the presenter moved the shared view
                    # it follows, or a jump to a saved view), this view is there now.
                    if self.following or camera.seq > self._seq:
                        self.camera = camera
                        self._seq = max(self._seq, camera.seq)
                    self._frames.put_nowait(frame)
            elif kind == "pick_result":
                future = self._picks.pop(event["id"], None)
                if future is not None and not future.done():
                    future.set_result([PickHit(**h) for h in event["hits"]])
            elif kind == "screenshot":
                shot = self._shot_frames.pop(event["frame"], None)
                future_shot = self._shots.pop(event["id"], None)
                if shot is not None and future_shot is not None and not future_shot.done():
                    future_shot.set_result(shot)
            elif kind == "role":  # a handover: either way, onto the shared view
                self.role, self._follows = event["role"], True
                if event.get("camera"):  # where the shared view is: the next camera follows on
                    self.camera = CameraState(**event["camera"])
                    self._seq = max(self._seq, self.camera.seq)
                self._note(event)
            elif kind == "participants":
                self.participants = event["participants"]
            elif kind == "annotations":
                self.annotations = event["annotations"]
            elif kind == "views":
                self.saved_views = event["views"]
            elif kind == "pointer":
                if event.get("position") is None:
                    self.pointers.pop(event["from"], None)
                else:
                    self.pointers[event["from"]] = event
            elif kind == "closing":
                self._note(event)
            elif kind not in ("heartbeat", "pong"):
                self._note(event)

    def _note(self, event: dict[str, Any]) -> None:
        self.events.append(event)
        del self.events[:-100]
        if self.on_event is not None:
            self.on_event(event)

    def _wake_all(self) -> None:
        for f in [*self._picks.values(), *self._shots.values()]:
            if not f.done():
                f.set_exception(self._failure or VastrayError(0, "closed", "the view closed"))
        self._frames.put_nowait(Frame(image=None))  # type: ignore[arg-type]  # a sentinel

    async def _ping(self) -> None:
        while not self._closed:
            await asyncio.sleep(PING_SECONDS)
            with contextlib.suppress(Exception):
                await self._send({"type": "ping", "t": time.time()})

    async def _send(self, message: dict[str, Any]) -> None:
        await self._connected.wait()
        await self._ws.send(json.dumps(message))

    async def _ack(self, frame: int) -> None:
        with contextlib.suppress(ConnectionClosed):
            await self._ws.send(json.dumps({"type": "ack", "frame": frame}))

    # -- controlling the view ---------------------------------------------------------------

    async def set_camera(
        self,
        eye: Sequence[float],
        target: Sequence[float],
        up: Sequence[float] | None = None,
        fov: float | None = None,
        projection: str | None = None,
    ) -> int:
        """Moves the camera; returns the seq that frames of this camera carry. Without
        `up`, `fov` or `projection` ("perspective" or "orthographic") it keeps the
        current one."""
        assert self.camera is not None
        if self.following:
            raise VastrayError(0, "following", "this view follows the presenter: follow(False) first")
        self._seq += 1
        self.camera = CameraState(
            seq=self._seq,
            eye=tuple(eye),
            target=tuple(target),  # type: ignore[arg-type]
            up=tuple(up) if up is not None else self.camera.up,  # type: ignore[arg-type]
            fov=fov if fov is not None else self.camera.fov,
            projection=projection if projection is not None else self.camera.projection,  # type: ignore[arg-type]
        )
        await self._send({"type": "camera", **self.camera.model_dump()})
        return self._seq

    @property
    def following(self) -> bool:
        """In a review, a follower showing the presenter's view: its `camera` is theirs,
        and it cannot move it."""
        return self.role == "follower" and self._follows

    async def follow(self, follow: bool = True) -> None:
        """In a review: show the presenter's view (True), or a view of one's own that
        starts where the shared one is (False: then this view's camera may move)."""
        await self._send({"type": "follow", "follow": follow})
        self._follows = follow

    async def annotate(self, text: str, position: Sequence[float]) -> None:
        """In a review: a note at a world position (a pick's), for everyone."""
        await self._send({"type": "annotate", "text": text, "position": list(position)})

    async def point(self, position: Sequence[float] | None) -> None:
        """In a review: a 3D point everyone sees with this participant's name (None:
        taken away)."""
        await self._send({"type": "pointer", "position": None if position is None else list(position)})

    async def save_view(self, name: str) -> None:
        """In a review: keeps this view (camera, quality, sections, highlight) under a name;
        `saved_views` lists them as the server says."""
        await self._send({"type": "save_view", "name": name})

    async def jump(self, view_id: str) -> None:
        """In a review: go to a saved view (the presenter moves everyone's shared view;
        anyone else goes free and moves there)."""
        await self._send({"type": "jump", "view": view_id})
        if self.role == "follower":
            self._follows = False

    async def handover(self, participant_id: str) -> None:
        """In a review, the presenter only: hands the presenter role to a participant
        (an id of `participants`)."""
        await self._send({"type": "handover", "to": participant_id})

    async def set_viewport(self, width: int, height: int) -> None:
        self.viewport = Viewport(width=width, height=height)
        await self._send({"type": "viewport", **self.viewport.model_dump()})

    async def set_quality(self, **changes: Any) -> None:
        """shading, pixels_of_error, ao_samples, jpeg_quality, refine, target_fps, ..."""
        await self._send({"type": "quality", **changes})

    async def set_sections(self, planes: Sequence[Plane]) -> None:
        """Section planes, (nx, ny, nz, offset) or SectionPlane: geometry where
        n . p + offset < 0 is cut; they replace the view's planes."""
        await self._send({"type": "sections", "planes": section_planes(planes)})

    async def set_section_box(
        self, bounds: tuple[tuple[float, float, float], tuple[float, float, float]], margin: float = 0.0
    ) -> None:
        """Keeps only what lies within `bounds` (lo, hi), grown by `margin` on every side:
        a part's bounds (`PartInfo.bounds`) cut the view down to that part and what is
        around it. Six section planes (`vastray.schemas.section_box`); they replace the
        view's planes, and `set_sections([])` takes them away."""
        await self.set_sections(section_box(*bounds, margin=margin))

    async def show(self, saved: dict[str, Any]) -> int:
        """Goes to a view saved with the model (one of `Client.model_views`): its section
        planes, highlighted parts and camera. Returns the seq that frames of it carry."""
        await self.set_sections([SectionPlane(**p) for p in saved.get("sections", [])])
        await self.set_highlight(list(saved.get("highlight", [])))
        c = saved["camera"]
        projection = c.get("projection", "perspective")
        return await self.set_camera(c["eye"], c["target"], c["up"], c["fov"], projection)

    async def set_highlight(self, parts: list[int]) -> None:
        """Parts to highlight (ids of the model's part table; `Client.parts` lists them)."""
        await self._send({"type": "highlight", "parts": [int(p) for p in parts]})

    # -- frames ----------------------------------------------------------------------------

    async def next_frame(self, timeout: float | None = 30.0) -> Frame:
        """The next frame (acknowledged as it is taken)."""
        frame = await asyncio.wait_for(self._frames.get(), timeout)
        if frame.image is None:
            raise self._failure or VastrayError(0, "closed", "the view closed")
        assert frame.header is not None
        await self._ack(frame.header.frame)
        return frame

    async def frames(self, timeout: float | None = 30.0) -> AsyncIterator[Frame]:
        while True:
            yield await self.next_frame(timeout)

    async def final(self, seq: int | None = None, timeout: float = 120.0) -> Frame:
        """The final (refined, complete) frame of camera `seq` (default: the latest set):
        the server is idle on this view afterwards."""
        want = self._seq if seq is None else seq
        deadline = time.monotonic() + timeout
        while True:
            frame = await self.next_frame(max(0.01, deadline - time.monotonic()))
            assert frame.header is not None
            if frame.header.camera_seq >= want and frame.final:
                return frame

    async def screenshot(self, timeout: float = 120.0) -> Frame:
        """A lossless PNG of the view once it is finished. Frames that arrive meanwhile
        are taken and acknowledged (and not returned by `next_frame`): the server sends
        the finished view only when the frames before it were acknowledged."""
        self._counter += 1
        shot_id = f"s{self._counter}"
        future: asyncio.Future[Frame] = asyncio.get_running_loop().create_future()
        self._shots[shot_id] = future
        await self._send({"type": "screenshot", "id": shot_id})
        deadline = time.monotonic() + timeout
        while not future.done():
            left = deadline - time.monotonic()
            if left <= 0:
                raise TimeoutError(f"no screenshot within {timeout} s")
            taking = asyncio.ensure_future(self._frames.get())
            await asyncio.wait({future, taking}, timeout=left, return_when=asyncio.FIRST_COMPLETED)
            if not taking.done():
                taking.cancel()
                continue
            frame = taking.result()
            if frame.image is None:
                raise self._failure or VastrayError(0, "closed", "the view closed")
            assert frame.header is not None
            await self._ack(frame.header.frame)
        return future.result()

    async def pick(self, points: Sequence[tuple[float, float]], timeout: float = 10.0) -> list[PickHit]:
        """Full-detail hits of image points (pixels of the viewport) of the current camera."""
        self._counter += 1
        pick_id = f"p{self._counter}"
        future: asyncio.Future[list[PickHit]] = asyncio.get_running_loop().create_future()
        self._picks[pick_id] = future
        camera = self.camera.model_dump() if self.camera is not None else None
        await self._send(
            {"type": "pick", "id": pick_id, "points": [list(p) for p in points], "camera": camera}
        )
        return await asyncio.wait_for(future, timeout)
