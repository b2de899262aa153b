"""Joining a still, finished shared view: it renders nothing more (it is idle), so a
participant who joins it late — or goes back to following it — gets its last frame at
once instead of a blank screen until the presenter moves."""

from __future__ import annotations

import asyncio
from typing import Any

import pytest
from serverproc import ServerProcess, wait_for_job
from test_reviews import Participant


@pytest.fixture(scope="module")
def model(server: ServerProcess) -> dict[str, Any]:
    with server.client() as api:
        job = api.post("/api/jobs", json={"source": "scene:spheres:5000:2"}).json()
        assert wait_for_job(api, job["id"])["state"] == "succeeded"
        return api.get(f"/api/models/{job['model_id']}").json()


def test_a_late_follower_of_an_idle_review_gets_its_last_frame(
    server: ServerProcess, model: dict[str, Any]
) -> None:
    with server.client() as api:
        review = api.post("/api/reviews", json={"model": model["id"]}).json()
    rid = review["review"]["id"]

    async def go() -> None:
        async with Participant(server, model["id"], rid, review["presenter_token"], "Ana") as ana:
            final = await ana.final()
            # Idle now: nothing more comes for the presenter.
            with pytest.raises(TimeoutError):
                await ana.until(lambda m: isinstance(m, type(final)), timeout=1.0)
            async with Participant(server, model["id"], rid, review["join_token"], "Bo") as bo:
                got = await bo.until(lambda m: isinstance(m, type(final)), timeout=10.0)
                assert got.final and got.camera_seq == final.camera_seq
                assert bo.frames[-1][1] == ana.frames[-1][1], "not the presenter's frame"

    asyncio.run(go())
