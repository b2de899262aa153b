"""The parts panel in a real Chromium: a model built from an OBJ with three named
objects lists them; a search highlights what it finds (the server's frames turn those
parts blue, the others grey); a click on a part frames it; a pick names
the part under the cursor. Its own server: the session's server shows the other browser
tests' model by default, and must not get a newer one."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from assembly import BOXES, build_assembly
from serverproc import ServerProcess


@pytest.fixture(scope="module")
def parts_server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ServerProcess]:
    with ServerProcess(tmp_path_factory.mktemp("parts") / "data", "--no-demo", "--cache", "64M") as s:
        yield s


@pytest.fixture(scope="module")
def assembly_model(parts_server: ServerProcess, tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    with parts_server.client() as api:
        return build_assembly(api, tmp_path_factory.mktemp("obj"))


def test_parts_are_listed_searched_highlighted_framed_and_picked(
    open_viewer: Any, parts_server: ServerProcess, assembly_model: dict[str, Any], tmp_path: Path
) -> None:
    v = open_viewer(f"{parts_server.open_url}&model={assembly_model['id']}")
    n = v.wait_final()
    v.js("() => window.vastray.setCamera({eye: [2.5, 0.5, 9], target: [2.5, 0.5, 0.5], up: [0, 1, 0]})")
    n = v.wait_final(n, v.js("window.vastray.seq"))
    page = v.page
    page.locator("#parts-panel summary").click()
    texts = page.locator("#parts li").all_inner_texts()
    assert len(texts) == len(BOXES) and all(any(t.startswith(b[0]) for t in texts) for b in BOXES), texts
    shown = v.shown()
    w, h = shown["width"], shown["height"]
    # Columns of the image where each box shows (the camera looks at x = 2.5 along -z).
    row = [(x + 0.5, h / 2) for x in range(0, int(w), 4)]
    before = v.pixels_at(row).astype(int)
    v.shot("before")

    # A search that finds nothing says so.
    page.locator("#parts-search").fill("no such thing")
    v.wait_for("() => document.getElementById('parts').innerText.includes('no part matches')")
    assert page.locator("#parts li").count() == 1

    page.locator("#parts-search").fill("valve")
    v.wait_for("() => document.querySelectorAll('#parts li').length === 1")
    sent = [m for m in v.sent if m["type"] == "highlight"]
    valve = next(p for p in v.js("window.vastray.panels.parts") if p["name"] == "Valve")
    assert sent and sent[-1]["parts"] == [valve["id"]]
    v.wait_final(n)
    n = v.frames()
    v.shot("valve-highlighted")
    after = v.pixels_at(row).astype(int)
    blue = (after[:, 2] - after[:, 0]) > 40
    xs = np.array([x for x, _ in row])
    assert blue.sum() >= 3 and not ((before[:, 2] - before[:, 0]) > 40).any(), "the valve turns blue"
    assert xs[blue].min() > 0.6 * w, "only the valve (the right-hand box) turns blue"

    # Clicking the part frames it: the camera turns to the valve's centre.
    page.locator("#parts li").first.click()
    v.wait_final(n, v.js("window.vastray.seq"))
    target = v.js("window.vastray.camera.target")
    np.testing.assert_allclose(target, [4.5, 0.5, 0.5], atol=1e-6)
    v.shot("valve-framed")

    # A table bigger than the welcome lists is searched on the server (GET .../parts):
    # make the page believe it has only the first part of many.
    v.js("() => { const p = window.vastray.panels; p.parts = p.parts.slice(0, 1); p.partsTotal = 50000; }")
    page.locator("#parts-search").fill("impeller")
    v.wait_for("() => document.querySelector('#parts li')?.innerText.startsWith('pump impeller')")
    assert page.locator("#parts li").count() == 1

    # A pick on the image centre (now the valve) names it.
    v.click_image(w / 2, h / 2)
    v.wait_for("() => document.getElementById('pick').innerText.includes('part:')")
    assert "part: Valve" in page.locator("#pick").inner_text()
