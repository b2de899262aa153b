"""A server restart: the page says it lost the connection, reconnects by itself when
the server is back (on the same port), and shows the view it had — its camera and its
quality settings — with new frames."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from conftest import build_model, free_port, not_blank
from serverproc import ServerProcess


@pytest.fixture
def restartable(tmp_path: Path) -> Iterator[list[ServerProcess]]:
    """A server on a fixed port (a restart comes back where the page looks for it); the
    list holds the server now running."""
    port = free_port()
    servers = [ServerProcess(tmp_path / "data", "--no-demo", "--cache", "128M", port=port)]
    servers[0].start()
    yield servers
    servers[-1].stop()


@pytest.mark.slow
def test_the_page_reconnects_after_a_server_restart(
    open_viewer: Any, restartable: list[ServerProcess]
) -> None:
    server = restartable[0]
    model = build_model(server)
    v = open_viewer(server.open_url)
    page = v.page
    n = v.wait_final()
    # A view of the user's own: moved, and shaded with normals.
    v.drag(120, 20)
    page.locator("#shading").select_option("normal")
    n = v.wait_final(n, v.js("window.vastray.seq"))
    v.wait_for("() => window.vastray.shown.header.stats.camera_seq === window.vastray.seq")
    camera = v.shown()["camera"]
    picture = v.thumbnail()

    server.stop()
    v.wait_for("() => document.getElementById('status').dataset.state === 'reconnecting'")
    v.shot("down")
    assert page.locator("#banner").is_visible() and "reconnecting" in page.locator("#banner").inner_text()
    # A pick meanwhile is refused with a notice, and then the banner says again what holds.
    v.click_image(*[x / 2 for x in (v.shown()["width"], v.shown()["height"])])
    v.wait_for("() => document.getElementById('banner').innerText.startsWith('Not connected')")
    v.wait_for("() => document.getElementById('banner').innerText.includes('reconnecting')")

    again = ServerProcess(server.data_dir, "--no-demo", "--cache", "128M", port=server.port)
    restartable.append(again)
    again.start()
    v.wait_for("() => document.getElementById('status').dataset.state === 'connected'")
    n = v.wait_final(n)
    v.shot("back")
    assert page.locator("#status").inner_text().startswith("connected")
    assert page.locator("#banner").is_hidden()
    assert page.locator("#model-select").input_value() == model["id"]
    # The same view as before the restart: the page gave the new server its camera and quality.
    assert v.shown()["camera"]["eye"] == pytest.approx(camera["eye"])
    assert page.locator("#shading").input_value() == "normal"
    hello = [m for m in v.sent if m["type"] == "hello"]
    assert len(hello) >= 2 and hello[-1]["quality"]["shading"] == "normal"
    assert not_blank(v.thumbnail())
    assert abs(v.thumbnail() - picture).mean() < 4, "not the picture the page had before the restart"
    # And it is live: a drag gets new frames.
    v.drag(-100, 0)
    v.wait_final(n, v.js("window.vastray.seq"))
