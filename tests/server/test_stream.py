"""Frame streaming against a real server, through raw WebSocket clients (the protocol
as docs/PROTOCOL.md specifies it): frames decode and show the model, a moved camera
changes the picture, a still view refines, completes and goes idle, several viewers of
two models at once, vanished clients reaped, reconnects resumed, bad messages answered
while the others are served, backpressure."""

from __future__ import annotations

import asyncio
import io
import json
import math
import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest
import websockets
from PIL import Image
from serverproc import ServerProcess, wait_for_job

from vastray.protocol import HEADER_SIZE, FrameHeader

pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning")


@pytest.fixture(scope="module")
def streaming(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ServerProcess]:
    # Quick pings, so a vanished client is noticed in seconds rather than a minute.
    s = ServerProcess(
        tmp_path_factory.mktemp("stream") / "data",
        "--no-demo",
        env={"VASTRAY_WS_PING_INTERVAL": "1", "VASTRAY_CLIENT_TIMEOUT": "20"},
    )
    s.start()
    yield s
    s.stop()


@pytest.fixture(scope="module")
def two_models(streaming: ServerProcess) -> dict[str, str]:
    out = {}
    with streaming.client() as api:
        for name, source in (("plant", "scene:plant:40000:3"), ("spheres", "scene:spheres:20000:1")):
            job = api.post("/api/jobs", json={"source": source, "name": name}).json()
            assert wait_for_job(api, job["id"])["state"] == "succeeded"
            out[name] = job["model_id"]
    return out


def ws_url(server: ServerProcess) -> str:
    return server.url.replace("http://", "ws://") + "/api/stream"


class Viewer:
    """A raw protocol client: hello, then frames and events as they come."""

    def __init__(self, server: ServerProcess, model: str, token: str | None = "key", **hello: Any) -> None:
        self.url = ws_url(server)
        self.hello = {
            "type": "hello",
            "protocol": 1,
            "model": model,
            "token": server.key if token == "key" else token,
            **hello,
        }
        self.ws: Any = None
        self.welcome: dict[str, Any] = {}
        self.frames: list[tuple[FrameHeader, np.ndarray]] = []
        self.events: list[dict[str, Any]] = []
        self.seq = 0

    async def __aenter__(self) -> Viewer:
        self.ws = await websockets.connect(self.url, max_size=1 << 26)
        await self.ws.send(json.dumps(self.hello))
        while True:
            m = json.loads(await asyncio.wait_for(self.ws.recv(), 30))
            if m["type"] == "welcome":
                self.welcome = m
                return self
            if m["type"] == "error" and m["fatal"]:
                raise RuntimeError(m["message"])

    async def __aexit__(self, *exc: object) -> None:
        await self.ws.close()

    async def recv(self, timeout: float = 30.0, ack: bool = True) -> Any:
        m = await asyncio.wait_for(self.ws.recv(), timeout)
        if isinstance(m, bytes):
            h = FrameHeader.unpack(m)
            image = np.asarray(Image.open(io.BytesIO(m[HEADER_SIZE:])).convert("RGB"))
            assert image.shape == (h.height, h.width, 3)
            self.frames.append((h, image))
            # Every frame is followed by its stats event (docs/PROTOCOL.md). It is owed now:
            # a caller's short poll must not drop the frame (and its ack) on a busy machine.
            stats = json.loads(await asyncio.wait_for(self.ws.recv(), max(timeout, 10.0)))
            assert stats["type"] == "stats" and stats["frame"] == h.frame, stats
            self.events.append(stats)
            if ack:
                await self.ws.send(json.dumps({"type": "ack", "frame": h.frame}))
            return h
        event = json.loads(m)
        self.events.append(event)
        return event

    async def until_final(self, seq: int | None = None, timeout: float = 60.0) -> FrameHeader:
        deadline = time.monotonic() + timeout
        want = self.seq if seq is None else seq
        while True:
            m = await self.recv(max(0.01, deadline - time.monotonic()))
            if isinstance(m, FrameHeader) and m.final and m.camera_seq >= want:
                return m

    async def until_error(self, timeout: float = 10.0) -> dict[str, Any]:
        deadline = time.monotonic() + timeout
        while True:
            m = await self.recv(max(0.01, deadline - time.monotonic()))
            if isinstance(m, dict) and m["type"] == "error":
                return m

    async def camera(self, eye: Any, target: Any, **extra: Any) -> int:
        self.seq += 1
        await self.send(
            {"type": "camera", "seq": self.seq, "eye": list(eye), "target": list(target), **extra}
        )
        return self.seq

    async def send(self, message: Any) -> None:
        await self.ws.send(message if isinstance(message, str) else json.dumps(message))

    async def quiet_for(self, seconds: float) -> list[Any]:
        """Everything that arrives within `seconds` (frames acked)."""
        got = []
        deadline = time.monotonic() + seconds
        while (left := deadline - time.monotonic()) > 0:
            try:
                got.append(await self.recv(left))
            except TimeoutError:
                break
        return got


def orbit(welcome: dict[str, Any], angle: float, distance: float = 1.0) -> tuple[list[float], list[float]]:
    lo, hi = (np.asarray(b) for b in welcome["model"]["bounds"])
    centre, size = (lo + hi) / 2, float(np.linalg.norm(hi - lo))
    eye = centre + size * distance * np.array([math.cos(angle), 0.6, math.sin(angle)])
    return eye.tolist(), centre.tolist()


def run(coro: Any) -> Any:
    return asyncio.run(coro)


def test_a_view_streams_refines_completes_and_idles(
    streaming: ServerProcess, two_models: dict[str, str]
) -> None:
    async def go() -> None:
        async with Viewer(streaming, two_models["plant"], viewport={"width": 320, "height": 200}) as v:
            w = v.welcome
            assert w["protocol"] == 1 and w["session"].startswith("ses-") and not w["resumed"]
            assert w["model"]["id"] == two_models["plant"] and w["viewport"]["width"] == 320
            final = await v.until_final(0)
            assert final.complete and final.width == 320 and final.height == 200 and final.scale == 1.0
            passes = [h.pass_number for h, _ in v.frames if h.camera_seq == 0]
            assert passes[-1] == w["quality"]["aa_passes"] and passes == sorted(passes)
            image = v.frames[-1][1].astype(int)
            assert (np.abs(image - image[0, 0]).sum(axis=2) > 30).mean() > 0.05, "blank frame"
            stats = [e for e in v.events if e["type"] == "stats"]
            assert (
                stats and stats[-1]["final"] and stats[-1]["complete"] and stats[-1]["working_set_bytes"] > 0
            )
            # Idle: nothing more for a still, finished view.
            assert [m for m in await v.quiet_for(1.5) if isinstance(m, FrameHeader)] == []
            # A moved camera: moving frames first, then refinement of that camera, and another picture.
            seq = await v.camera(*orbit(w, 2.0, 0.8))
            moved = await v.until_final(seq)
            assert moved.complete
            mine = [h for h, _ in v.frames if h.camera_seq == seq]
            assert mine[0].pass_number == 0 and mine[0].moving
            assert np.abs(v.frames[-1][1].astype(int) - image).mean() > 3, (
                "the camera moved, the picture did not"
            )
            # Stats answer the frame they follow, with the camera seq they answer.
            last = [e for e in v.events if e["type"] == "stats"][-1]
            assert last["frame"] == moved.frame and last["camera_seq"] == seq and last["latency_ms"] > 0

    run(go())


def test_quality_changes_take_effect(streaming: ServerProcess, two_models: dict[str, str]) -> None:
    async def go() -> None:
        async with Viewer(streaming, two_models["spheres"], viewport={"width": 160, "height": 120}) as v:
            await v.until_final(0)
            headlight = v.frames[-1][1]
            await v.send({"type": "quality", "shading": "normal", "aa_passes": 1})
            h = await v.until_final(0)
            assert h.pass_number == 1
            assert np.abs(v.frames[-1][1].astype(int) - headlight.astype(int)).mean() > 5
            await v.send({"type": "viewport", "width": 200, "height": 100})
            h = await v.until_final(0)
            assert (h.width, h.height) == (200, 100)
            await v.send({"type": "quality", "refine": False, "pixels_of_error": 8})
            h = await v.until_final(0)
            assert h.pixels_of_error == 8 and h.pass_number == 1

    run(go())


def test_several_viewers_of_two_models(streaming: ServerProcess, two_models: dict[str, str]) -> None:
    async def one(model: str, angle: float) -> FrameHeader:
        async with Viewer(streaming, model, viewport={"width": 200, "height": 150}) as v:
            await v.until_final(0)
            seq = await v.camera(*orbit(v.welcome, angle))
            return await v.until_final(seq)

    async def go() -> list[FrameHeader]:
        jobs = [one(two_models["plant" if i % 2 else "spheres"], 0.5 * i) for i in range(6)]
        return await asyncio.gather(*jobs)

    finals = run(go())
    assert len(finals) == 6 and all(f.complete for f in finals)


def test_bad_messages_get_errors_and_the_others_are_served(
    streaming: ServerProcess, two_models: dict[str, str]
) -> None:
    cases: list[tuple[Any, str]] = [
        ("{not json", "malformed JSON"),
        ('["a list"]', "JSON object"),
        ({"type": "teleport"}, "unknown message type"),
        ({"type": "camera", "seq": 1, "eye": [math.nan, 0, 0], "target": [0, 0, 0]}, "finite"),
        ({"type": "camera", "seq": 1, "eye": [1, 2, 3], "target": [1, 2, 3]}, "eye and target"),
        ({"type": "camera", "seq": 1, "eye": [0, 5, 0], "target": [0, 0, 0], "up": [0, 1, 0]}, "parallel"),
        ({"type": "camera", "seq": 1, "eye": [1, 2, 3], "target": [0, 0, 0], "fov": 0}, "fov"),
        ({"type": "camera", "seq": 1, "eye": [1, 2, 3], "target": [0, 0, 0], "fov": 180}, "fov"),
        ({"type": "viewport", "width": 100000, "height": 100000}, "width"),
        ({"type": "viewport", "width": 10000, "height": 10000}, "pixel budget"),
        (
            {"type": "camera", "seq": 1, "eye": [1, 2, 3], "target": [0, 0, 0], "projection": "fisheye"},
            "camera: projection: Input should be 'perspective' or 'orthographic'",
        ),
        ({"type": "quality", "shading": "phong"}, "quality: shading: "),
        ({"type": "ack"}, "frame"),
    ]

    async def go() -> None:
        async with (
            Viewer(streaming, two_models["plant"], viewport={"width": 120, "height": 90}) as bad,
            Viewer(streaming, two_models["spheres"], viewport={"width": 120, "height": 90}) as good,
        ):
            await bad.until_final(0)
            await good.until_final(0)
            for message, text in cases:
                json_text = message if isinstance(message, str) else json.dumps(message)
                await bad.send(json_text)
                error = await bad.until_error()
                assert text in error["message"] and not error["fatal"], (message, error)
                seq = await good.camera(*orbit(good.welcome, len(good.frames)))
                assert (await good.until_final(seq)).complete
            await bad.ws.send(b"\x00binary")
            assert "binary" in (await bad.until_error())["message"]
            # The misbehaving viewer itself still works.
            seq = await bad.camera(*orbit(bad.welcome, 1.0))
            assert (await bad.until_final(seq)).complete

    run(go())


def test_refusals(streaming: ServerProcess, two_models: dict[str, str]) -> None:
    with streaming.client() as api:
        other_token = api.post(f"/api/models/{two_models['spheres']}/tokens", json={}).json()["token"]

    async def closed_with(hello: dict[str, Any] | str | None) -> tuple[int, dict[str, Any]]:
        async with websockets.connect(ws_url(streaming)) as ws:
            if hello is not None:
                await ws.send(hello if isinstance(hello, str) else json.dumps(hello))
            message = json.loads(await asyncio.wait_for(ws.recv(), 30))
            with pytest.raises(websockets.ConnectionClosed) as closed:
                while True:
                    await asyncio.wait_for(ws.recv(), 30)
            return closed.value.rcvd.code, message

    base = {"type": "hello", "protocol": 1, "model": two_models["plant"]}
    on_target = {"eye": [1, 2, 3], "target": [1, 2, 3]}
    for hello, code, text in [
        (base, 4401, "needs an API key or a viewing token"),
        ({**base, "token": "nope"}, 4401, "not valid"),
        ({**base, "token": other_token}, 4403, "does not grant access"),
        ({**base, "token": streaming.key, "model": "mdl-nosuch"}, 4404, "no model"),
        ({**base, "token": streaming.key, "protocol": 99}, 4400, "protocol"),
        ("hello?", 4400, "hello"),
        ({**base, "token": streaming.key, "viewport": {"width": 9000, "height": 9000}}, 4400, "pixel budget"),
        # A camera no frame can come from (each field valid, together not).
        ({**base, "token": streaming.key, "camera": on_target}, 4400, "coincide"),
    ]:
        got, message = run(closed_with(hello))
        assert got == code and text in message["message"] and message["fatal"], (hello, got, message)

    # A viewing token for the model is enough.
    with streaming.client() as api:
        token = api.post(f"/api/models/{two_models['plant']}/tokens", json={}).json()["token"]

    async def with_token() -> None:
        async with Viewer(
            streaming, two_models["plant"], token=token, viewport={"width": 64, "height": 48}
        ) as v:
            assert (await v.until_final(0)).complete

    run(with_token())


def test_reconnect_resumes_the_view(streaming: ServerProcess, two_models: dict[str, str]) -> None:
    async def go() -> None:
        async with Viewer(streaming, two_models["plant"], viewport={"width": 100, "height": 80}) as v:
            await v.until_final(0)
            seq = await v.camera(*orbit(v.welcome, 2.5, 0.7), fov=60)
            await v.send({"type": "quality", "shading": "sun"})
            await v.until_final(seq)
            session, camera = v.welcome["session"], v.frames[-1][0].camera_seq
            v.ws.transport.abort()  # the network goes, no close handshake
        async with Viewer(streaming, two_models["plant"], session=session) as again:
            w = again.welcome
            assert w["resumed"] and w["session"] == session
            assert w["camera"]["seq"] == camera and w["camera"]["fov"] == 60
            assert w["quality"]["shading"] == "sun" and w["viewport"]["width"] == 100
            assert (await again.until_final(camera)).width == 100

    run(go())


def viewers_now(server: ServerProcess) -> float:
    text = httpx.get(f"{server.url}/metrics").text
    return float(next(line for line in text.splitlines() if line.startswith("vastray_viewers ")).split()[1])


def stream_frames(server: ServerProcess) -> float:
    text = httpx.get(f"{server.url}/metrics").text
    line = next((x for x in text.splitlines() if x.startswith('vastray_frames_total{kind="stream"}')), None)
    return float(line.split()[1]) if line else 0.0


def test_a_vanished_client_is_reaped_and_its_rendering_stops(
    streaming: ServerProcess, two_models: dict[str, str], tmp_path: Path
) -> None:
    """A client process frozen (SIGSTOP) mid-stream with its camera moving: it sends
    nothing, closes nothing. The server's pings go unanswered; it drops the viewer and
    its view stops rendering."""
    script = tmp_path / "client.py"
    script.write_text(f"""
import asyncio, json, math, sys, websockets
async def main():
    async with websockets.connect({ws_url(streaming)!r}) as ws:
        await ws.send(json.dumps({{"type": "hello", "protocol": 1, "model": {two_models["plant"]!r},
                                  "token": {streaming.key!r}, "viewport": {{"width": 320, "height": 240}}}}))
        print("connected", flush=True)
        i = 0
        while True:
            i += 1
            eye = [60 * math.cos(0.1 * i), 30, 60 * math.sin(0.1 * i)]
            await ws.send(json.dumps({{"type": "camera", "seq": i, "eye": eye, "target": [0, 8, 0]}}))
            try:
                m = await asyncio.wait_for(ws.recv(), 0.05)
            except TimeoutError:
                continue
            if isinstance(m, bytes):
                await ws.send(json.dumps({{"type": "ack", "frame": int.from_bytes(m[8:12], "little")}}))
asyncio.run(main())
""")
    before = viewers_now(streaming)
    proc = subprocess.Popen([sys.executable, str(script)], stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout is not None and proc.stdout.readline().strip() == "connected"
        deadline = time.monotonic() + 30
        while stream_frames(streaming) == 0 or viewers_now(streaming) <= before:
            assert time.monotonic() < deadline, "the client never got frames"
            time.sleep(0.1)
        time.sleep(1.0)
        os.kill(proc.pid, signal.SIGSTOP)
        deadline = time.monotonic() + 20
        while viewers_now(streaming) > before:
            assert time.monotonic() < deadline, "the vanished client was never reaped"
            time.sleep(0.2)
        frames = stream_frames(streaming)
        time.sleep(1.5)
        assert stream_frames(streaming) == frames, "its view kept rendering"
    finally:
        os.kill(proc.pid, signal.SIGCONT)
        proc.kill()
        proc.wait()


def test_disconnect_mid_frame(streaming: ServerProcess, two_models: dict[str, str]) -> None:
    async def go() -> None:
        async with Viewer(streaming, two_models["spheres"], viewport={"width": 120, "height": 90}) as other:
            await other.until_final(0)
            for i in range(5):
                v = Viewer(streaming, two_models["plant"], viewport={"width": 640, "height": 480})
                await v.__aenter__()
                await v.camera(*orbit(v.welcome, 0.3 * i))
                await asyncio.sleep(0.02 * i)
                if i % 2:
                    v.ws.transport.abort()
                else:
                    await v.ws.close()
            seq = await other.camera(*orbit(other.welcome, 1.3))
            assert (await other.until_final(seq)).complete

    run(go())
    assert "Traceback" not in streaming.log()


def test_a_slow_reader_gets_fewer_frames_and_a_fast_one_keeps_its_rate(
    streaming: ServerProcess, two_models: dict[str, str]
) -> None:
    """Both cameras move all the time; the slow client acknowledges a frame every 0.4 s.
    It gets a frame per acknowledgement at most (never a backlog), while the fast one
    gets many; nothing stale reaches either."""

    async def drive(v: Viewer, seconds: float, slow: bool) -> int:
        end = time.monotonic() + seconds
        count = 0
        i = 0
        while time.monotonic() < end:
            i += 1
            await v.camera(*orbit(v.welcome, 0.05 * i))
            try:
                m = await v.recv(0.02 if not slow else 0.4, ack=False)
            except TimeoutError:
                continue
            if isinstance(m, FrameHeader):
                count += 1
                if slow:
                    await asyncio.sleep(0.4)
                await v.send({"type": "ack", "frame": m.frame})
        return count

    async def go() -> tuple[int, int, Viewer, Viewer]:
        async with (
            Viewer(streaming, two_models["spheres"], viewport={"width": 160, "height": 120}) as fast,
            Viewer(streaming, two_models["spheres"], viewport={"width": 160, "height": 120}) as slow,
        ):
            n_fast, n_slow = await asyncio.gather(drive(fast, 4.0, False), drive(slow, 4.0, True))
            return n_fast, n_slow, fast, slow

    n_fast, n_slow, fast, slow = run(go())
    assert n_slow <= 4.0 / 0.4 + 3, n_slow
    assert n_fast > 3 * n_slow, (n_fast, n_slow)
    for v in (fast, slow):
        seqs = [h.camera_seq for h, _ in v.frames]
        numbers = [h.frame for h, _ in v.frames]
        assert seqs == sorted(seqs) and numbers == sorted(numbers), "a frame older than one already sent"


def test_flooding_client_is_cut_off_alone(tmp_path: Path) -> None:
    s = ServerProcess(tmp_path / "data", "--no-demo").start()
    try:
        with s.client() as api:
            job = api.post("/api/jobs", json={"source": "scene:spheres:2000:1"}).json()
            model = wait_for_job(api, job["id"])["model_id"]

        async def go() -> tuple[int, bool]:
            async with (
                Viewer(s, model, viewport={"width": 64, "height": 48}) as flood,
                Viewer(s, model, viewport={"width": 64, "height": 48}) as calm,
            ):
                limited = False
                end = time.monotonic() + 12
                code = 0
                try:
                    while time.monotonic() < end:
                        for _ in range(200):
                            await flood.send({"type": "ping"})
                        await asyncio.sleep(0.01)
                        while True:
                            try:
                                m = await flood.recv(0.001)
                            except TimeoutError:
                                break
                            if isinstance(m, dict) and m.get("code") == "rate_limited":
                                limited = True
                except websockets.ConnectionClosed as closed:
                    code = closed.rcvd.code if closed.rcvd else 0
                seq = await calm.camera(*orbit(calm.welcome, 0.7))
                assert (await calm.until_final(seq)).complete
                return code, limited

        code, limited = run(go())
        assert limited and code == 1008
    finally:
        s.stop()
