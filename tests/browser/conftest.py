"""Fixtures of the browser tests: Debian's Chromium driven by Playwright (no browser
download), a real `vastray serve` with a small built model, and a `Viewer` around a
page of it.

Nothing here sleeps to wait: the page marks its canvas as frames arrive (`data-frames`
counts the frames drawn, `data-final`, `data-complete`, `data-moving`, `data-camera-seq`
describe the last) and exposes its App object as `window.vastray`; the tests wait on
those. Every test leaves screenshots in `out/test-artifacts/browser/`, named after it.
"""

from __future__ import annotations

import json
import re
import shutil
import socket
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "server"))
from serverproc import ServerProcess, wait_for_job

REPO = Path(__file__).resolve().parents[2]
ARTIFACTS = REPO / "out" / "test-artifacts" / "browser"
WINDOW = {"width": 820, "height": 520}  # the stage is what the 300-pixel side panel leaves
MODEL_SOURCE = "scene:plant:40000:1"
NETWORK_ERROR = re.compile(r"^(WebSocket connection to .* failed|Failed to load resource)")
WAIT_MS = 60_000  # for frames on a busy 2-core machine; never a time the tests assert


def chromium_path() -> str:
    path = shutil.which("chromium") or shutil.which("chromium-browser")
    if path is None:
        pytest.fail("Debian's chromium is needed for the browser tests (apt-get install chromium)")
    return path


@pytest.fixture(scope="module")
def browser() -> Iterator[Any]:
    """Per module: Playwright's sync API keeps an event loop running on the main thread
    while it is open, and tests after the browser tests call asyncio.run."""
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        b = p.chromium.launch(executable_path=chromium_path(), args=["--no-sandbox"])
        yield b
        b.close()


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def build_model(server: ServerProcess, source: str = MODEL_SOURCE, name: str = "plant") -> dict[str, Any]:
    with server.client() as api:
        job = api.post("/api/jobs", json={"source": source, "name": name}).json()
        assert wait_for_job(api, job["id"])["state"] == "succeeded"
        return api.get(f"/api/models/{job['model_id']}").json()


@pytest.fixture(scope="session")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ServerProcess]:
    """One server for the browser tests that do not restart it."""
    with ServerProcess(tmp_path_factory.mktemp("browser") / "data", "--no-demo", "--cache", "256M") as s:
        yield s


@pytest.fixture(scope="session")
def model(server: ServerProcess) -> dict[str, Any]:
    return build_model(server)


@pytest.fixture(scope="session")
def api(server: ServerProcess) -> Iterator[httpx.Client]:
    with server.client() as c:
        yield c


class Viewer:
    """A page of the viewer in its own browser context, with what the tests ask of it."""

    def __init__(self, browser: Any, name: str, artifacts: Path) -> None:
        self.name = name
        self.artifacts = artifacts
        self.context = browser.new_context(viewport=WINDOW, accept_downloads=True)
        self.page = self.context.new_page()
        self.errors: list[str] = []  # uncaught exceptions and console errors
        self.sent: list[dict[str, Any]] = []  # JSON messages the page sent on its WebSockets
        self.received: list[dict[str, Any]] = []  # JSON events it received
        self.page.on("pageerror", lambda e: self.errors.append(f"uncaught: {e}"))
        self.page.on("console", self._console)
        self.page.on("websocket", self._websocket)

    def _console(self, message: Any) -> None:
        # The browser's own report of a connection that failed (a server down) is not the
        # page's error: the page says so in its status and banner.
        if message.type == "error" and not NETWORK_ERROR.search(message.text):
            self.errors.append(f"console: {message.text}")

    def _websocket(self, ws: Any) -> None:
        def keep(into: list[dict[str, Any]], payload: Any) -> None:
            if isinstance(payload, str):
                into.append(json.loads(payload))

        ws.on("framesent", lambda payload: keep(self.sent, payload))
        ws.on("framereceived", lambda payload: keep(self.received, payload))

    def close(self) -> None:
        self.context.close()

    def shot(self, step: str) -> Path:
        path = self.artifacts / f"{self.name}-{step}.png"
        self.page.screenshot(path=str(path))
        return path

    def js(self, expression: str, arg: Any = None) -> Any:
        return self.page.evaluate(expression, arg)

    # -- waiting on the canvas -------------------------------------------------------------

    def frames(self) -> int:
        return int(self.js("Number(document.getElementById('view').dataset.frames ?? 0)"))

    def wait_final(self, after: int = 0, seq: int | None = None) -> int:
        """Waits for a final frame drawn after the first `after` frames (and showing the
        camera `seq` or a newer one); returns the frames drawn."""
        self.page.wait_for_function(
            """([after, seq]) => {
                const d = document.getElementById('view').dataset;
                return Number(d.frames ?? 0) > after && d.final === 'true'
                    && (seq === null || Number(d.cameraSeq) >= seq);
            }""",
            arg=[after, seq],
            timeout=WAIT_MS,
        )
        return self.frames()

    def wait_for(self, expression: str, arg: Any = None) -> Any:
        return self.page.wait_for_function(expression, arg=arg, timeout=WAIT_MS).json_value()

    def record_frames(self) -> None:
        """From now on, `window.__frames` lists every frame the stream delivers."""
        self.js(
            """() => {
                window.__frames = [];
                window.vastray.stream.addEventListener('frame', (e) => window.__frames.push(
                    {moving: e.detail.moving, final: e.detail.final, seq: e.detail.cameraSeq,
                     pass: e.detail.pass, poe: e.detail.pixelsOfError}));
            }"""
        )

    # -- pixels -----------------------------------------------------------------------------

    def thumbnail(self, width: int = 96, height: int = 64) -> np.ndarray:
        """The canvas scaled down, as an (height, width, 3) int array."""
        data = self.js(
            """([w, h]) => {
                const t = document.createElement('canvas');
                t.width = w; t.height = h;
                const c = t.getContext('2d');
                c.drawImage(document.getElementById('view'), 0, 0, w, h);
                return Array.from(c.getImageData(0, 0, w, h).data);
            }""",
            [width, height],
        )
        return np.asarray(data, dtype=int).reshape(height, width, 4)[..., :3]

    def pixels_at(self, points: list[tuple[float, float]]) -> np.ndarray:
        """The canvas's pixels at image points of the frame shown, as (n, 3) ints."""
        data = self.js(
            """(points) => {
                const app = window.vastray, {rect} = app.shown;
                const ctx = app.canvas.getContext('2d');
                return points.map(([x, y]) => {
                    const cx = Math.floor(rect.x + x * rect.width / rect.fullW);
                    const cy = Math.floor(rect.y + y * rect.height / rect.fullH);
                    return Array.from(ctx.getImageData(cx, cy, 1, 1).data.slice(0, 3));
                });
            }""",
            points,
        )
        return np.asarray(data, dtype=int).reshape(-1, 3)

    # -- the frame shown and where its pixels are on the page -------------------------------

    def shown(self) -> dict[str, Any]:
        """The camera and size of the frame on the canvas."""
        return self.js(
            """() => {
                const {camera, rect} = window.vastray.shown;
                return {camera: {eye: camera.eye, target: camera.target, up: camera.up, fov: camera.fov,
                                 projection: camera.projection},
                        width: Math.round(rect.fullW), height: Math.round(rect.fullH)};
            }"""
        )

    def page_point(self, x: float, y: float) -> tuple[float, float]:
        """Where image point (x, y) of the frame shown is on the page (CSS pixels)."""
        return tuple(
            self.js(
                """([x, y]) => {
                    const app = window.vastray, {rect} = app.shown, canvas = app.canvas;
                    const box = canvas.getBoundingClientRect(), css = canvas.clientWidth / canvas.width;
                    return [box.left + (rect.x + x * rect.width / rect.fullW) * css,
                            box.top + (rect.y + y * rect.height / rect.fullH) * css];
                }""",
                [x, y],
            )
        )

    def stream_pick(self, points: list[tuple[float, float]]) -> list[dict[str, Any]]:
        """Picks through image points of the frame shown, over the page's own stream (so
        with its view's settings, as a click would)."""
        return self.js(
            """(points) => new Promise((resolve) => {
                const app = window.vastray, {camera, rect, header} = app.shown;
                const id = `test-${Math.random()}`;
                const answer = (e) => {
                    if (e.detail.id !== id) return;
                    app.stream.removeEventListener('pick_result', answer);
                    resolve(e.detail.hits);
                };
                app.stream.addEventListener('pick_result', answer);
                app.stream.send({type: 'pick', id, points, camera: camera.toMessage(header.cameraSeq),
                                 width: Math.round(rect.fullW), height: Math.round(rect.fullH)});
            })""",
            points,
        )

    def click_image(self, x: float, y: float) -> None:
        px, py = self.page_point(x, y)
        self.page.mouse.click(px, py)

    def drag(self, dx: float, dy: float = 0.0, steps: int = 12) -> None:
        """A left-button drag across the middle of the canvas (an orbit)."""
        box = self.page.locator("#view").bounding_box()
        assert box is not None
        x, y = box["x"] + box["width"] / 2, box["y"] + box["height"] / 2
        self.page.mouse.move(x, y)
        self.page.mouse.down()
        self.page.mouse.move(x + dx, y + dy, steps=steps)
        self.page.mouse.up()

    def errors_received(self) -> list[dict[str, Any]]:
        return [m for m in self.received if m.get("type") == "error"]


@pytest.fixture
def artifacts(request: pytest.FixtureRequest) -> Path:
    ARTIFACTS.mkdir(parents=True, exist_ok=True)
    for old in ARTIFACTS.glob(f"{request.node.name}-*.png"):
        old.unlink()
    return ARTIFACTS


@pytest.fixture
def open_viewer(browser: Any, request: pytest.FixtureRequest, artifacts: Path) -> Iterator[Any]:
    """`open_viewer(url, role="page")`: a Viewer at `url`. At the end every viewer's last
    screenshot is saved, and an uncaught JavaScript error fails the test."""
    viewers: list[Viewer] = []

    def open_(url: str, role: str = "page") -> Viewer:
        name = re.sub(r"[^\w.-]+", "_", f"{request.node.name}-{role}")
        v = Viewer(browser, name, artifacts)
        viewers.append(v)
        v.page.goto(url)
        return v

    yield open_
    errors = []
    for v in viewers:
        try:
            v.shot("end")
        except Exception as exc:  # a closed page has no screenshot; say so, go on
            errors.append(f"{v.name}: no screenshot ({exc})")
        errors += [f"{v.name}: {e}" for e in v.errors]
        v.close()
    assert not errors, "\n".join(errors)


def pick(
    api: httpx.Client, model_id: str, shown: dict[str, Any], points: list[tuple[float, float]]
) -> list[Any]:
    """Full-detail picks through image points of the camera of a frame shown (REST)."""
    camera = {
        k: shown["camera"][k] for k in ("eye", "target", "up", "fov", "projection") if k in shown["camera"]
    }
    camera.update(width=shown["width"], height=shown["height"])
    r = api.post(f"/api/models/{model_id}/pick", json={"camera": camera, "points": [list(p) for p in points]})
    assert r.status_code == 200, r.text
    return r.json()["hits"]


def grid(shown: dict[str, Any], nx: int, ny: int, margin: float = 0.1) -> list[tuple[float, float]]:
    """Image points on an nx x ny grid inside the frame (pixel centres)."""
    w, h = shown["width"], shown["height"]
    xs = np.linspace(margin * w, (1 - margin) * w, nx)
    ys = np.linspace(margin * h, (1 - margin) * h, ny)
    return [(float(int(x)) + 0.5, float(int(y)) + 0.5) for y in ys for x in xs]


def not_blank(image: np.ndarray) -> bool:
    """A picture, not a single colour: a good share of pixels far from the corner's."""
    far = np.abs(image - image[0, 0]).sum(axis=-1) > 40
    return bool(far.mean() > 0.05 and len(np.unique(image.reshape(-1, 3), axis=0)) > 50)
