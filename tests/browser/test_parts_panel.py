"""The parts panel in a real Chromium: a model built from an OBJ with three named
objects lists them; a search highlights what it finds (the server's frames turn those
parts blue, the others grey); a click on a part frames it; a pick names
the part under the cursor; a section box keeps a highlighted or picked part and what
lies around it. Its own server: the session's server shows the other browser
tests' model by default, and must not get a newer one."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from assembly import BOXES, build_assembly
from serverproc import ServerProcess

from vastray.schemas import section_box


@pytest.fixture(scope="module")
def parts_server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ServerProcess]:
    with ServerProcess(tmp_path_factory.mktemp("parts") / "data", "--no-demo", "--cache", "64M") as s:
        yield s


@pytest.fixture(scope="module")
def assembly_model(parts_server: ServerProcess, tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    with parts_server.client() as api:
        return build_assembly(api, tmp_path_factory.mktemp("obj"))


def open_parts_panel(open_viewer: Any, server: ServerProcess, model: dict[str, Any]) -> tuple[Any, int]:
    """The page on the assembly, looking along -z at the three boxes in a row, with the
    parts panel open; and the frames drawn so far."""
    v = open_viewer(f"{server.open_url}&model={model['id']}")
    n = v.wait_final()
    v.js("() => window.vastray.setCamera({eye: [2.5, 0.5, 9], target: [2.5, 0.5, 0.5], up: [0, 1, 0]})")
    n = v.wait_final(n, v.js("window.vastray.seq"))
    v.page.locator("#parts-panel summary").click()
    return v, n


def test_parts_are_listed_searched_highlighted_framed_and_picked(
    open_viewer: Any, parts_server: ServerProcess, assembly_model: dict[str, Any], tmp_path: Path
) -> None:
    v, n = open_parts_panel(open_viewer, parts_server, assembly_model)
    page = v.page
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
    # and gives its size along the axes (the valve is a unit cube: BOXES).
    assert "part size: 1.000 × 1.000 × 1.000" in page.locator("#pick").inner_text()

    # "Box this part" highlights the picked part and boxes it, its bounds found on the
    # server when the page has not been sent them.
    v.js("() => window.vastray.panels.partBounds.clear()")
    sends = len(v.sent)
    page.locator("#pick-part-box").click()
    v.wait_for("() => window.vastray.panels.sections.length === 6")
    planes = [m for m in v.sent[sends:] if m["type"] == "sections"][-1]["planes"]
    lo, hi = (4.0, 0.0, 0.0), (5.0, 1.0, 1.0)  # the valve (BOXES)
    expected = section_box(lo, hi, margin=float(np.linalg.norm(np.subtract(hi, lo))) / 50)
    assert [(p["normal"], pytest.approx(p["offset"])) for p in planes] == [
        (list(e.normal), e.offset) for e in expected
    ]
    assert [m for m in v.sent[sends:] if m["type"] == "highlight"][-1]["parts"] == [valve["id"]]
    assert not v.errors_received()


def test_a_section_box_keeps_the_highlighted_part(
    open_viewer: Any, parts_server: ServerProcess, assembly_model: dict[str, Any]
) -> None:
    """'box' in the section panel keeps only what lies in a box around the highlighted
    parts (grown by a fiftieth of its diagonal): six planes, as vastray.schemas.section_box
    makes them; the parts beside it leave the picture and the picks, the highlighted one
    stays as it was; a seventh plane is refused with a notice; "clear" takes them away."""
    v, n = open_parts_panel(open_viewer, parts_server, assembly_model)
    page = v.page
    page.locator("#parts-search").fill("impeller")
    v.wait_for("() => document.querySelectorAll('#parts li').length === 1")
    v.wait_final(n)
    n = v.frames()
    shown = v.shown()
    w = int(shown["width"])
    row = [(x + 0.5, shown["height"] / 2) for x in range(0, w, -(-w // 60))]  # a pick takes 64 points at most
    hits = v.stream_pick(row)
    impeller = [p for p, h in zip(row, hits, strict=True) if h["hit"] and 1.99 <= h["position"][0] <= 3.01]
    beside = [p for p, h in zip(row, hits, strict=True) if h["hit"] and not 1.5 <= h["position"][0] <= 3.5]
    assert len(impeller) >= 3 and len(beside) >= 3, (len(impeller), len(beside))
    before_impeller, before_beside = v.pixels_at(impeller), v.pixels_at(beside)

    page.locator("#sections-panel summary").click()
    page.locator("#section-box").click()
    v.wait_for("() => window.vastray.panels.sections.length === 6")
    sent = [m for m in v.sent if m["type"] == "sections"][-1]["planes"]
    impeller_part = next(p for p in v.js("window.vastray.panels.parts") if p["name"] == "pump impeller")
    lo, hi = impeller_part["bounds"]
    expected = section_box(lo, hi, margin=float(np.linalg.norm(np.subtract(hi, lo))) / 50)
    assert len(sent) == 6
    for got, want in zip(sent, expected, strict=True):
        np.testing.assert_allclose(got["normal"], want.normal)
        assert got["offset"] == pytest.approx(want.offset) and got["enabled"]
    v.wait_final(n)
    v.shot("section-box")
    assert not any(h["hit"] for h in v.stream_pick(beside)), "the parts beside the box should be cut away"
    assert [h["hit"] for h in v.stream_pick(impeller)] == [True] * len(impeller)
    changed = lambda a, b: np.abs(a - b).sum(axis=-1) > 40  # noqa: E731
    assert changed(v.pixels_at(impeller), before_impeller).mean() < 0.2
    assert changed(v.pixels_at(beside), before_beside).mean() > 0.8
    # The overlay draws the box's twelve edges around the impeller, clear of the parts
    # beside it, and no box once a plane is off.
    box = v.page.locator("#overlay path.section-box")
    assert box.count() == 1 and box.get_attribute("d").count("M") == 12
    r = box.bounding_box()
    assert r is not None
    inside = lambda x, y: r["x"] <= x <= r["x"] + r["width"] and r["y"] <= y <= r["y"] + r["height"]  # noqa: E731
    assert all(inside(*v.page_point(x, y)) for x, y in impeller)
    assert not any(inside(*v.page_point(x, y)) for x, y in beside)
    page.get_by_role("checkbox", name="X plane on").first.uncheck()
    v.wait_for("() => !document.querySelector('#overlay path.section-box')")
    page.get_by_role("checkbox", name="X plane on").first.check()
    v.wait_for("() => document.querySelector('#overlay path.section-box') !== null")
    # Six planes are all a view takes: "+ X" says so and sends nothing.
    sends = len(v.sent)
    page.get_by_role("button", name="add a section plane across X").click()
    v.wait_for("() => document.body.innerText.includes('section planes at most')")
    assert v.js("window.vastray.panels.sections.length") == 6
    assert not [m for m in v.sent[sends:] if m["type"] == "sections"]
    # "clear" takes them all away: the parts beside come back.
    page.click("#section-clear")
    v.wait_for("() => !document.querySelector('#overlay path.section-box')")
    assert [m for m in v.sent if m["type"] == "sections"][-1]["planes"] == []
    assert all(h["hit"] for h in v.stream_pick(beside))
    # A highlighted part whose bounds the page was not sent (as past the welcome's list)
    # gets the same box: "box" asks the server for them by id.
    v.js("() => window.vastray.panels.partBounds.clear()")
    page.locator("#section-box").click()
    v.wait_for("() => window.vastray.panels.sections.length === 6")
    again = [m for m in v.sent if m["type"] == "sections"][-1]["planes"]
    assert [(p["normal"], pytest.approx(p["offset"])) for p in again] == [
        (p["normal"], p["offset"]) for p in sent
    ]
    assert not v.errors_received()
