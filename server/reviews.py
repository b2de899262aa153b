"""Design reviews (paper 002 ch. 1): one presenter, many participants, one model.

A review session (in memory, while anyone is in it) holds the **shared view**: the
presenter drives its camera, sections, highlight and quality; participants who follow
subscribe to it and receive the very same encoded frames (rendered and encoded once per
review, not once per participant). A participant who navigates freely gets a view of
its own, starting from the shared one, and can jump back. The presenter role moves only
when the presenter hands it over. Pointers are broadcast; annotations and saved views
are kept in the registry with the review.
"""

from __future__ import annotations

import asyncio
import logging
import secrets
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from vastray.protocol import (
    AnnotateMessage,
    CameraState,
    FollowMessage,
    HandoverMessage,
    JumpMessage,
    PointerMessage,
    RenameMessage,
    SaveViewMessage,
    StreamQuality,
)
from vastray.server.views import View

if TYPE_CHECKING:
    from vastray.server.stream import Connection, StreamHub

log = logging.getLogger("vastray.reviews")
REVIEW_MESSAGES = ("follow", "pointer", "annotate", "save_view", "jump", "handover", "rename")


@dataclass
class Participant:
    id: str
    name: str
    role: str  # presenter or follower
    following: bool
    conn: Connection

    def describe(self) -> dict[str, Any]:
        return {"id": self.id, "name": self.name, "role": self.role, "following": self.following}


class ReviewSession:
    def __init__(self, hub: StreamHub, review: dict[str, Any]) -> None:
        self.hub = hub
        self.id = review["id"]
        self.model_id = review["model_id"]
        self.title = review["title"]
        self.saved_state: dict[str, Any] = review.get("state") or {}
        self.shared: View | None = None
        self.participants: dict[str, Participant] = {}
        self.pointers: dict[str, dict[str, Any]] = {}

    @property
    def registry(self) -> Any:
        return self.hub.state.registry

    @property
    def presenter(self) -> Participant | None:
        return next((p for p in self.participants.values() if p.role == "presenter"), None)

    # -- joining and leaving ---------------------------------------------------------------

    def join(self, conn: Connection, name: str | None, wants_presenter: bool) -> Participant:
        role = "presenter" if wants_presenter and self.presenter is None else "follower"
        pid = f"pt-{secrets.token_hex(4)}"
        label = (
            name or ""
        ).strip() or f"{'presenter' if role == 'presenter' else 'participant'} {len(self.participants) + 1}"
        participant = Participant(pid, label, role, True, conn)
        self.participants[pid] = participant
        log.info("review %s: %s joined as %s", self.id, label, role)
        return participant

    async def leave(self, participant: Participant) -> None:
        self.participants.pop(participant.id, None)
        if self.pointers.pop(participant.id, None) is not None:
            self.broadcast(
                {"type": "pointer", "from": participant.id, "name": participant.name, "position": None}
            )
        if self.shared is not None:
            self.saved_state = self.shared.state()
            await asyncio.to_thread(self.registry.update_review_state, self.id, self.saved_state)
        self.broadcast_participants()
        if not self.participants:
            self.hub.reviews.pop(self.id, None)

    def welcome(self, participant: Participant) -> dict[str, Any]:
        presenter = self.presenter
        return {
            "id": self.id,
            "title": self.title,
            "role": participant.role,
            "participant": participant.id,
            "name": participant.name,
            "presenter": presenter.id if presenter else None,
            "following": participant.following,
        }

    def initial_camera(self) -> CameraState | None:
        camera = self.saved_state.get("camera")
        return CameraState(**camera) if camera else None

    def initial_quality(self) -> StreamQuality | None:
        """The quality the shared view was left at, or was started with."""
        quality = self.saved_state.get("quality")
        return StreamQuality(**quality) if quality else None

    # -- telling everyone ------------------------------------------------------------------

    def broadcast(self, event: dict[str, Any]) -> None:
        for p in self.participants.values():
            p.conn.event(event)

    def broadcast_participants(self) -> None:
        presenter = self.presenter
        self.broadcast(
            {
                "type": "participants",
                "presenter": presenter.id if presenter else None,
                "participants": [p.describe() for p in self.participants.values()],
            }
        )

    async def send_state(self, participant: Participant) -> None:
        """What a joining participant needs besides frames: people, pointers, notes, views."""
        self.broadcast_participants()
        for pid, pointer in self.pointers.items():
            participant.conn.event({"type": "pointer", "from": pid, **pointer})
        participant.conn.event(await self._annotations())
        participant.conn.event(await self._views())

    # The registry is read and written off the event loop.
    async def _annotations(self) -> dict[str, Any]:
        return {
            "type": "annotations",
            "annotations": await asyncio.to_thread(self.registry.annotations, self.id),
        }

    async def _views(self) -> dict[str, Any]:
        saved = await asyncio.to_thread(self.registry.saved_views, self.id)
        return {"type": "views", "views": [{"id": v["id"], "name": v["name"], **v["state"]} for v in saved]}

    # -- messages --------------------------------------------------------------------------

    def may_drive(self, participant: Participant) -> bool:
        """Whether this participant's camera and settings messages change its view: the
        presenter's change the shared view, a free participant's its own."""
        return participant.role == "presenter" or not participant.following

    async def handle(self, participant: Participant, msg: Any) -> None:
        conn = participant.conn
        if isinstance(msg, FollowMessage):
            if participant.role == "presenter":
                conn.event(
                    {
                        "type": "error",
                        "code": "presenter",
                        "fatal": False,
                        "message": "the presenter drives the shared view; hand the role over to go free",
                    }
                )
                return
            participant.following = msg.follow
            conn.follow(self.shared if msg.follow else None)
            self.broadcast_participants()
        elif isinstance(msg, RenameMessage):
            participant.name = msg.name.strip() or participant.name
            self.broadcast_participants()
        elif isinstance(msg, PointerMessage):
            if msg.position is None:
                self.pointers.pop(participant.id, None)
            else:
                self.pointers[participant.id] = {"name": participant.name, "position": list(msg.position)}
            self.broadcast(
                {
                    "type": "pointer",
                    "from": participant.id,
                    "name": participant.name,
                    "position": list(msg.position) if msg.position else None,
                }
            )
        elif isinstance(msg, AnnotateMessage):
            view = conn.view
            camera = view.camera.model_dump() if view is not None else None
            await asyncio.to_thread(
                self.registry.add_annotation,
                f"note-{secrets.token_hex(5)}",
                self.id,
                participant.name,
                msg.text,
                list(msg.position),
                camera,
            )
            self.broadcast(await self._annotations())
        elif isinstance(msg, SaveViewMessage):
            view = conn.view
            if view is not None:
                view_id = f"view-{secrets.token_hex(5)}"
                await asyncio.to_thread(
                    self.registry.add_saved_view, view_id, self.id, msg.name, view.state()
                )
                self.broadcast(await self._views())
        elif isinstance(msg, JumpMessage):
            views = await asyncio.to_thread(self.registry.saved_views, self.id)
            saved = next((v for v in views if v["id"] == msg.view), None)
            if saved is None:
                conn.event(
                    {
                        "type": "error",
                        "code": "no_such_view",
                        "message": f"no saved view {msg.view!r}",
                        "fatal": False,
                    }
                )
                return
            if participant.role == "presenter" and self.shared is not None:
                self.shared.apply(saved["state"])
            else:
                if participant.following:
                    participant.following = False
                    conn.follow(None)
                    self.broadcast_participants()
                if conn.view is not None:
                    conn.view.apply(saved["state"])
            self.hub.scheduler.notify()
        elif isinstance(msg, HandoverMessage):
            target = self.participants.get(msg.to)
            if participant.role != "presenter":
                conn.event(
                    {
                        "type": "error",
                        "code": "not_presenter",
                        "fatal": False,
                        "message": "only the presenter can hand the presenter role over",
                    }
                )
                return
            if target is None or target is participant:
                conn.event(
                    {
                        "type": "error",
                        "code": "no_such_participant",
                        "fatal": False,
                        "message": f"no other participant {msg.to!r} in this review",
                    }
                )
                return
            participant.role, target.role = "follower", "presenter"
            participant.following = True
            if not target.following:
                # The new presenter takes the shared view from where it looked on its own.
                if target.conn.view is not None and self.shared is not None:
                    self.shared.apply(target.conn.view.state())
                target.following = True
                target.conn.follow(self.shared)
            # ... and in the shape of its own window, as the presenter's frames always are
            # (everyone else letterboxes them).
            if self.shared is not None and target.conn.viewport is not None:
                if target.conn.viewport != self.shared.viewport:
                    self.shared.set_viewport(target.conn.viewport)
            log.info("review %s: %s handed the presenter role to %s", self.id, participant.name, target.name)
            # With the shared view's camera: its seq is the one the new presenter's next
            # camera must exceed, before any frame of the shared view has reached it.
            shared = {"camera": self.shared.camera.model_dump()} if self.shared is not None else {}
            participant.conn.event({"type": "role", "role": "follower", "presenter": target.id, **shared})
            target.conn.event({"type": "role", "role": "presenter", "presenter": target.id, **shared})
            self.broadcast_participants()


def new_review_id() -> str:
    return f"rev-{secrets.token_hex(6)}"


def review_urls(base: str, review_id: str, presenter: str, follower: str) -> dict[str, str]:
    return {
        "presenter_url": f"{base}/?review={review_id}&token={presenter}",
        "join_url": f"{base}/?review={review_id}&token={follower}",
    }
