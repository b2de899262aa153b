"""Design reviews against a real server: links with presenter and follower tokens;
followers receive the presenter's very frames (rendered and encoded once); only the
presenter drives the shared view; a follower goes free and comes back; an explicit
handover; pointers, annotations and saved views shared and kept in the registry."""

from __future__ import annotations

import asyncio
import json
from collections.abc import Iterator
from typing import Any

import httpx
import pytest
import websockets
from serverproc import ServerProcess, wait_for_job

from vastray.protocol import HEADER_SIZE, FrameHeader


@pytest.fixture(scope="module")
def srv(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ServerProcess]:
    s = ServerProcess(tmp_path_factory.mktemp("reviews") / "data", "--no-demo")
    s.start()
    yield s
    s.stop()


@pytest.fixture(scope="module")
def model(srv: ServerProcess) -> dict[str, Any]:
    with srv.client() as api:
        job = api.post("/api/jobs", json={"source": "scene:plant:20000:5"}).json()
        wait_for_job(api, job["id"])
        return api.get(f"/api/models/{job['model_id']}").json()


@pytest.fixture()
def review(srv: ServerProcess, model: dict[str, Any]) -> dict[str, Any]:
    with srv.client() as api:
        r = api.post("/api/reviews", json={"model": model["id"], "title": "pump room"})
        assert r.status_code == 201, r.text
        return r.json()


class Participant:
    def __init__(self, srv: ServerProcess, model: str, review: str, token: str, name: str) -> None:
        self.url = srv.url.replace("http://", "ws://") + "/api/stream"
        self.hello = {
            "type": "hello",
            "protocol": 1,
            "model": model,
            "review": review,
            "token": token,
            "name": name,
            "viewport": {"width": 160, "height": 120},
        }
        self.frames: list[tuple[FrameHeader, bytes]] = []
        self.events: list[dict[str, Any]] = []

    async def __aenter__(self) -> Participant:
        self.ws = await websockets.connect(self.url)
        await self.ws.send(json.dumps(self.hello))
        while True:
            m = json.loads(await asyncio.wait_for(self.ws.recv(), 30))
            if m["type"] == "welcome":
                self.welcome = m
                return self
            assert m["type"] != "error", m

    async def __aexit__(self, *exc: object) -> None:
        await self.ws.close()

    async def send(self, **message: Any) -> None:
        await self.ws.send(json.dumps(message))

    async def next(self, timeout: float = 30.0) -> Any:
        m = await asyncio.wait_for(self.ws.recv(), timeout)
        if isinstance(m, bytes):
            h = FrameHeader.unpack(m)
            self.frames.append((h, m[HEADER_SIZE:]))
            await self.send(type="ack", frame=h.frame)
            return h
        event = json.loads(m)
        self.events.append(event)
        return event

    async def until(self, test: Any, timeout: float = 60.0) -> Any:
        deadline = asyncio.get_running_loop().time() + timeout
        while True:
            m = await self.next(max(0.01, deadline - asyncio.get_running_loop().time()))
            if test(m):
                return m

    async def final(self, seq: int | None = None) -> FrameHeader:
        return await self.until(
            lambda m: isinstance(m, FrameHeader) and m.final and (seq is None or m.camera_seq == seq)
        )

    async def event(self, kind: str, test: Any = lambda e: True) -> dict[str, Any]:
        return await self.until(lambda m: isinstance(m, dict) and m["type"] == kind and test(m))


def orbit(model: dict[str, Any], k: int) -> dict[str, Any]:
    (lx, ly, lz), (hx, hy, hz) = model["bounds"]
    c = [(lx + hx) / 2, (ly + hy) / 2, (lz + hz) / 2]
    return {"eye": [c[0] + 30 + 5 * k, c[1] + 20, c[2] + 30 - 7 * k], "target": c}


def test_followers_get_the_presenters_frames(
    srv: ServerProcess, model: dict[str, Any], review: dict[str, Any]
) -> None:
    rid = review["review"]["id"]
    assert review["presenter_url"].endswith(f"/?review={rid}&token={review['presenter_token']}")
    assert review["join_url"].endswith(f"/?review={rid}&token={review['join_token']}")

    async def go() -> None:
        async with (
            Participant(srv, model["id"], rid, review["presenter_token"], "Ana") as ana,
            Participant(srv, model["id"], rid, review["join_token"], "Bo") as bo,
            Participant(srv, model["id"], rid, review["join_token"], "Cy") as cy,
        ):
            assert ana.welcome["review"]["role"] == "presenter" and bo.welcome["review"]["role"] == "follower"
            parts = await cy.event("participants", lambda e: len(e["participants"]) == 3)
            assert {p["name"] for p in parts["participants"]} == {"Ana", "Bo", "Cy"}
            await ana.send(type="camera", seq=1, **orbit(model, 1))
            finals = await asyncio.gather(ana.final(1), bo.final(1), cy.final(1))
            # The same encoded frame for everyone: one render, one encode.
            images = {p.frames[-1][1] for p in (ana, bo, cy)}
            assert len(images) == 1 and all(f.camera_seq == 1 for f in finals)
            # A follower cannot drive the shared view.
            await bo.send(type="camera", seq=5, **orbit(model, 2))
            error = await bo.event("error")
            assert "follow the presenter" in error["message"]
            # Going free: its own view; the others are not moved.
            await bo.send(type="follow", follow=False)
            await bo.send(type="camera", seq=7, **orbit(model, 3))
            mine = await bo.final(7)
            assert mine.camera_seq == 7
            await ana.send(type="camera", seq=2, **orbit(model, 4))
            await ana.final(2)
            await cy.final(2)
            assert bo.frames[-1][0].camera_seq == 7, "a free participant was moved by the presenter"
            # Back to following: the presenter's view again.
            await bo.send(type="follow", follow=True)
            back = await bo.final()
            assert back.camera_seq == 2 and bo.frames[-1][1] == cy.frames[-1][1]

    asyncio.run(go())


def test_pointer_annotations_views_and_handover(
    srv: ServerProcess, model: dict[str, Any], review: dict[str, Any]
) -> None:
    rid = review["review"]["id"]

    async def go() -> None:
        async with (
            Participant(srv, model["id"], rid, review["presenter_token"], "Ana") as ana,
            Participant(srv, model["id"], rid, review["join_token"], "Bo") as bo,
        ):
            await bo.send(type="rename", name="Bo Lindqvist")
            named = await ana.event(
                "participants", lambda e: any(p["name"] == "Bo Lindqvist" for p in e["participants"])
            )
            assert {p["name"] for p in named["participants"]} == {"Ana", "Bo Lindqvist"}
            centre = orbit(model, 0)["target"]
            await ana.send(type="pointer", position=centre)
            pointer = await bo.event("pointer")
            assert pointer["position"] == centre and pointer["name"] == "Ana"
            await bo.send(type="annotate", text="check this flange", position=centre)
            notes = await ana.event("annotations", lambda e: e["annotations"])
            assert notes["annotations"][-1]["text"] == "check this flange"
            assert notes["annotations"][-1]["author"] == "Bo Lindqvist"
            await ana.send(type="camera", seq=3, **orbit(model, 5))
            await ana.final(3)
            await ana.send(type="save_view", name="overview")
            views = await bo.event("views", lambda e: e["views"])
            saved = views["views"][-1]
            assert saved["name"] == "overview" and saved["camera"]["eye"] == orbit(model, 5)["eye"]
            # Move away, jump back: everyone who follows goes there.
            await ana.send(type="camera", seq=4, **orbit(model, 6))
            await ana.final(4)
            await bo.final(4)
            await ana.send(type="jump", view=saved["id"])
            landed = await bo.until(lambda m: isinstance(m, FrameHeader) and m.final and m.camera_seq > 4)
            assert landed.complete
            # Only the presenter hands over; then the roles swap.
            await bo.send(type="handover", to=ana.welcome["review"]["participant"])
            assert "only the presenter" in (await bo.event("error"))["message"]
            await ana.send(type="handover", to=bo.welcome["review"]["participant"])
            role = await bo.event("role")
            assert role["role"] == "presenter"
            # Where the shared view is (the jump above), with its seq: the new
            # presenter's next camera must be newer, before any of its frames arrive.
            assert role["camera"]["seq"] > 4 and role["camera"]["eye"] == orbit(model, 5)["eye"]
            assert (await ana.event("role"))["camera"] == role["camera"]
            await bo.send(type="camera", seq=10, **orbit(model, 7))
            assert (await ana.final(10)).camera_seq == 10

    asyncio.run(go())
    # Kept in the registry with the review.
    with srv.client() as api:
        info = api.get(f"/api/reviews/{rid}").json()
        assert [a["text"] for a in info["annotations"]] == ["check this flange"]
        assert [v["name"] for v in info["views"]] == ["overview"]
    with srv.client(key=review["join_token"]) as follower:
        assert follower.get(f"/api/reviews/{rid}").status_code == 200
        assert follower.post("/api/reviews", json={"model": model["id"]}).status_code == 403
        # A review link shows the review's model, and only it.
        assert [m["id"] for m in follower.get("/api/models").json()] == [model["id"]]
        assert follower.get(f"/api/models/{model['id']}").status_code == 200


def test_review_links_are_checked(srv: ServerProcess, model: dict[str, Any], review: dict[str, Any]) -> None:
    rid = review["review"]["id"]
    with srv.client() as api:
        token = api.post(f"/api/models/{model['id']}/tokens", json={}).json()["token"]
        assert api.post("/api/reviews", json={"model": "mdl-nosuch"}).status_code == 404
        other = api.post("/api/reviews", json={"model": model["id"]}).json()

    async def refused(hello: dict[str, Any]) -> int:
        async with websockets.connect(srv.url.replace("http://", "ws://") + "/api/stream") as ws:
            await ws.send(json.dumps({"type": "hello", "protocol": 1, "model": model["id"], **hello}))
            with pytest.raises(websockets.ConnectionClosed) as closed:
                while True:
                    await asyncio.wait_for(ws.recv(), 30)
            return closed.value.rcvd.code

    assert asyncio.run(refused({"review": rid, "token": token})) == 4403  # a model token is not a review link
    assert (
        asyncio.run(refused({"review": rid, "token": other["join_token"]})) == 4403
    )  # another review's link
    assert asyncio.run(refused({"review": "rev-000000000000", "token": srv.key})) == 4404
    with httpx.Client(base_url=srv.url) as anon:
        assert anon.get(f"/api/reviews/{rid}").status_code == 401


def test_a_review_starts_from_the_view_it_was_started_with(srv: ServerProcess, model: dict[str, Any]) -> None:
    """The page starts a review from what it shows: the shared view starts there (camera,
    shading, section planes), not at the model's overview, for whoever joins first."""
    camera = {"seq": 7, **orbit(model, 3), "fov": 40.0}
    (lx, _, _), (hx, _, _) = model["bounds"]
    plane = {"normal": [1.0, 0.0, 0.0], "offset": -(lx + hx) / 2}  # cuts away the half below x's middle
    view = {"camera": camera, "quality": {"shading": "sun", "pixels_of_error": 2.0}, "sections": [plane]}
    with srv.client() as api:
        r = api.post("/api/reviews", json={"model": model["id"], "title": "from here", "view": view})
        assert r.status_code == 201, r.text
        started = r.json()
        # A view that is not one is refused, with what is wrong, and no review is made.
        before = len(api.get("/api/reviews").json())
        bad = api.post("/api/reviews", json={"model": model["id"], "view": {"camera": {"eye": [0, 0, 0]}}})
        assert bad.status_code == 422 and bad.json()["error"]["code"] == "invalid_request"
        assert "target" in bad.json()["error"]["message"]
        on_target = {"camera": {"eye": camera["target"], "target": camera["target"]}}
        bad = api.post("/api/reviews", json={"model": model["id"], "view": on_target})
        assert bad.status_code == 422 and bad.json()["error"]["code"] == "invalid_camera"
        assert "coincide" in bad.json()["error"]["message"]
        assert len(api.get("/api/reviews").json()) == before

    async def run() -> None:
        rid = started["review"]["id"]
        # The follower joins first: it, too, sees the view the review was started with.
        async with Participant(srv, model["id"], rid, started["join_token"], "early") as early:
            assert early.welcome["camera"]["eye"] == pytest.approx(camera["eye"])
            assert early.welcome["camera"]["target"] == pytest.approx(camera["target"])
            assert early.welcome["camera"]["fov"] == camera["fov"]
            assert early.welcome["quality"]["shading"] == "sun"
            assert early.welcome["quality"]["pixels_of_error"] == 2.0
            assert early.welcome["sections"] == [{**plane, "enabled": True}]
            async with Participant(srv, model["id"], rid, started["presenter_token"], "lead") as lead:
                assert lead.welcome["review"]["role"] == "presenter"
                assert lead.welcome["camera"]["eye"] == pytest.approx(camera["eye"])
                assert lead.welcome["quality"]["shading"] == "sun"
                await lead.final()

    asyncio.run(run())
