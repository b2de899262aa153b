"""The viewer page in a real Chromium against a real server: it loads and shows the
model, dragging moves the view (moving frames, then a final one), the wheel zooms towards
the cursor, the keyboard orbits, pans and zooms, quality settings take
effect, picks measure distances at full detail, a double click turns the view to a point,
screenshots download, and a section plane hides the geometry on its cut side."""

from __future__ import annotations

import base64
import subprocess
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from conftest import build_model, grid, not_blank, pick
from PIL import Image
from serverproc import VASTRAY


def test_the_page_loads_and_shows_the_model(open_viewer: Any, server: Any, model: dict[str, Any]) -> None:
    v = open_viewer(server.open_url)
    v.wait_final()
    v.shot("loaded")
    page = v.page
    assert page.title() == "vastray"
    assert page.locator("#status").get_attribute("data-state") == "connected"
    assert page.locator("#status").inner_text() == "connected"
    assert page.locator("#banner").is_hidden()
    # The model picker shows the model, and the URL names it (a reload opens it again).
    assert page.locator("#model-select").input_value() == model["id"]
    assert "plant" in page.locator("#model-select option:checked").inner_text()
    assert f"model={model['id']}" in page.url
    # The canvas shows a picture, not one colour, complete and refined.
    assert not_blank(v.thumbnail()), "the canvas is blank"
    stats = page.locator("#stats").inner_text()
    assert "complete\tyes" in stats and "(final)" in stats, stats
    # With the API key, uploads are offered.
    assert page.locator("#upload-button").is_visible()


def test_dragging_changes_the_view(open_viewer: Any, server: Any, model: dict[str, Any]) -> None:
    v = open_viewer(server.open_url)
    n = v.wait_final()
    before, eye = v.thumbnail(), v.shown()["camera"]["eye"]
    v.record_frames()
    v.drag(160, 40)
    v.shot("dragging")
    seq = v.js("window.vastray.seq")
    assert seq > 0, "dragging sent no camera"
    v.wait_final(n, seq)
    v.shot("after")
    frames = v.js("window.__frames")
    mine = [f for f in frames if f["seq"] >= 1]
    assert any(f["moving"] for f in mine), f"no moving frame while dragging: {frames}"
    first_final = next(i for i, f in enumerate(mine) if f["final"])
    assert any(f["moving"] for f in mine[:first_final]), "the final frame came before any moving one"
    assert mine[-1]["final"] and mine[-1]["seq"] == seq
    # The view the page shows is the camera it drove, and the picture changed.
    assert v.shown()["camera"]["eye"] != eye
    assert np.abs(v.thumbnail() - before).mean() > 8, "the camera moved, the picture did not"
    assert not v.errors_received()


def test_quality_changes_take_effect(open_viewer: Any, server: Any, model: dict[str, Any]) -> None:
    v = open_viewer(server.open_url)
    n = v.wait_final()
    headlight = v.thumbnail()
    page = v.page
    page.locator("#shading").select_option("normal")
    n = v.wait_final(n)
    v.shot("normals")
    normals = v.thumbnail()
    assert np.abs(normals - headlight).mean() > 15, "shading 'normal' did not change the colours"
    # Normals shading is colourful where headlight shading is nearly grey.
    saturation = lambda im: (im.max(axis=-1) - im.min(axis=-1)).mean()  # noqa: E731
    assert saturation(normals) > saturation(headlight) + 10
    assert [m for m in v.sent if m["type"] == "quality"][-1]["shading"] == "normal"

    # Pixels of error: the slider, by keyboard as a user might (steps of 0.25 from 1 to 4).
    slider = page.locator("#poe")
    slider.focus()
    for _ in range(12):
        slider.press("ArrowRight")
    assert page.locator("#poe-value").inner_text() == "4"
    v.wait_for(
        "() => window.vastray.panels.header?.pixelsOfError === 4 && "
        "document.getElementById('view').dataset.final === 'true'"
    )
    v.shot("poe4")
    stats = page.locator("#stats").inner_text()
    assert "pixels of error\t4.00" in stats, stats
    # The page stays usable: no errors from the server about any of it.
    assert not v.errors_received(), v.errors_received()


def test_a_pick_measures_a_distance(open_viewer: Any, server: Any, api: Any, model: dict[str, Any]) -> None:
    v = open_viewer(server.open_url)
    v.wait_final()
    shown = v.shown()
    points = grid(shown, 9, 7)
    hits = pick(api, model["id"], shown, points)
    hit = [(p, h) for p, h in zip(points, hits, strict=True) if h["hit"]]
    assert len(hit) >= 4, "the model should fill much of the view"
    # Two hits far apart on the image.
    (a, _), (b, _) = max(
        ((x, y) for x in hit for y in hit), key=lambda xy: np.hypot(*np.subtract(xy[0][0], xy[1][0]))
    )
    v.click_image(*a)
    v.wait_for("() => document.getElementById('pick').innerText.startsWith('point:')")
    v.click_image(*b)
    v.wait_for("() => document.getElementById('pick').dataset.distance !== undefined")
    v.shot("measured")
    text = v.page.locator("#pick").inner_text()
    assert text.startswith("A → B: "), text
    shown_distance = float(v.page.locator("#pick").get_attribute("data-distance"))
    # The page's picks are the server's full-detail answers for the rays it asked about.
    asked = [m for m in v.sent if m["type"] == "pick"]
    assert len(asked) == 2
    again = [
        pick(
            api,
            model["id"],
            {**shown, "camera": m["camera"], "width": m["width"], "height": m["height"]},
            m["points"],
        )[0]
        for m in asked
    ]
    assert all(h["hit"] for h in again)
    expected = float(np.linalg.norm(np.subtract(again[0]["position"], again[1]["position"])))
    assert shown_distance == pytest.approx(expected, rel=1e-6)
    assert float(text.splitlines()[0].removeprefix("A → B: ")) == pytest.approx(expected, rel=1e-3)
    # Its components along the axes, and the angle between the two surfaces' planes.
    delta = np.subtract(again[1]["position"], again[0]["position"])
    shown_delta = [float(x) for x in v.page.locator("#pick").get_attribute("data-delta").split(",")]
    np.testing.assert_allclose(shown_delta, delta, rtol=1e-6, atol=1e-9 * expected)
    components = text.splitlines()[1].split(", ")
    assert [c[:3] for c in components] == ["Δx ", "Δy ", "Δz "], components
    np.testing.assert_allclose([float(c[3:]) for c in components], delta, rtol=1e-3, atol=1e-3 * expected)
    normals = [np.asarray(h["normal"]) / np.linalg.norm(h["normal"]) for h in again]
    angle = np.degrees(np.arccos(min(1.0, abs(float(normals[0] @ normals[1])))))
    assert float(v.page.locator("#pick").get_attribute("data-angle")) == pytest.approx(angle, abs=1e-6)
    assert text.splitlines()[2] == f"angle between the surfaces: {angle:.1f}°"
    overlay = v.page.locator("#overlay")
    # Units: the model says none, so lengths go bare. Said on the page (with the API key),
    # every length gives them, the overlay's label too, and the model keeps them.
    model_url = f"/api/models/{model['id']}"
    assert api.get(model_url).json()["units"] is None
    v.page.select_option("#model-units", "mm")
    v.wait_for("() => document.getElementById('pick').innerText.split('\\n')[0].endsWith(' mm')")
    lines = v.page.locator("#pick").inner_text().splitlines()
    assert float(lines[0].removeprefix("A → B: ").removesuffix(" mm")) == pytest.approx(expected, rel=1e-3)
    assert [c[-3:] for c in lines[1].split(", ")] == [" mm"] * 3, lines[1]
    assert lines[3].startswith("point: ") and lines[3].endswith(" (mm)"), lines[3]
    assert lines[4].startswith("distance from the eye: ") and lines[4].endswith(" mm"), lines[4]
    assert (overlay.locator("text.distance").text_content() or "").endswith(" mm")
    v.wait_for("() => document.body.innerText.includes('its lengths are in mm')")
    assert api.get(model_url).json()["units"] == "mm"
    v.page.select_option("#model-units", "")
    v.wait_for("() => document.body.innerText.includes('its units are not said')")
    assert not v.page.locator("#pick").inner_text().splitlines()[0].endswith(" mm")
    assert api.get(model_url).json()["units"] is None
    # Units said elsewhere (here over the API) reach the open page at once.
    api.patch(model_url, json={"units": "ft"}).raise_for_status()
    v.wait_for("() => document.getElementById('pick').innerText.split('\\n')[0].endsWith(' ft')")
    assert v.page.locator("#model-units").input_value() == "ft"
    api.patch(model_url, json={"units": ""}).raise_for_status()
    v.wait_for("() => document.getElementById('model-units').value === ''")
    # A rename reaches the model picker the same way.
    name = api.get(model_url).json()["name"]
    picked = "() => document.getElementById('model-select').selectedOptions[0].text"
    api.patch(model_url, json={"name": "renamed for the test"}).raise_for_status()
    v.wait_for(f"() => ({picked})().startsWith('renamed for the test (')")
    api.patch(model_url, json={"name": name}).raise_for_status()
    v.wait_for(f"() => ({picked})().startsWith({name + ' ('!r})")
    # Overlays: two markers and the measured line, pinned to the points as the camera moves.
    assert overlay.locator("circle.marker").count() == 2 and overlay.locator("line").count() == 1
    x0 = float(overlay.locator("circle.marker").first.get_attribute("cx"))
    n = v.frames()
    v.drag(120, 0)
    v.wait_final(n, v.js("window.vastray.seq"))
    x1 = float(overlay.locator("circle.marker").first.get_attribute("cx"))
    assert abs(x1 - x0) > 5, "the marker did not follow its point"
    v.shot("moved")
    # A click on nothing says so.
    v.click_image(2.5, 2.5)
    v.wait_for("() => document.getElementById('pick').innerText.startsWith('Nothing there')")


def test_the_keyboard_orbits_pans_and_zooms(open_viewer: Any, server: Any, model: dict[str, Any]) -> None:
    """Without a mouse: an arrow key orbits as a 15-pixel drag does (about the target, at
    the same distance, 0.09 rad about the model's up), shift+arrow pans (eye and target
    move alike, by a twentieth of the view's height at the target), + and - zoom by a
    fifth; in a text box the arrows are the box's."""
    v = open_viewer(server.open_url)
    n = v.wait_final()

    def camera() -> dict[str, np.ndarray]:
        c = v.js("() => ({...window.vastray.camera})")
        return {"eye": np.asarray(c["eye"]), "target": np.asarray(c["target"]), "fov": c["fov"]}

    v.page.locator("#view").focus()
    before = camera()
    v.page.keyboard.press("ArrowRight")
    after = camera()
    offset0, offset1 = before["eye"] - before["target"], after["eye"] - after["target"]
    np.testing.assert_allclose(after["target"], before["target"], rtol=1e-12)
    assert np.linalg.norm(offset1) == pytest.approx(np.linalg.norm(offset0), rel=1e-12)
    # (about +y, the plant's up)
    turned = np.arctan2(offset1[0], offset1[2]) - np.arctan2(offset0[0], offset0[2])
    assert abs(turned) == pytest.approx(15 * 0.006, abs=1e-9) and offset1[1] == pytest.approx(offset0[1])

    before = after
    v.page.keyboard.press("Shift+ArrowUp")
    after = camera()
    moved = after["eye"] - before["eye"]
    np.testing.assert_allclose(after["target"] - before["target"], moved, atol=1e-9)
    distance = float(np.linalg.norm(before["eye"] - before["target"]))
    tan = np.tan(np.radians(before["fov"] / 2))
    assert np.linalg.norm(moved) == pytest.approx(tan * distance / 10, rel=1e-9)

    v.page.keyboard.press("+")
    assert np.linalg.norm(camera()["eye"] - after["target"]) == pytest.approx(0.8 * distance, rel=1e-9)
    v.page.keyboard.press("-")
    assert np.linalg.norm(camera()["eye"] - after["target"]) == pytest.approx(distance, rel=1e-9)

    before = camera()
    v.page.locator("#parts-panel summary").click()
    v.page.locator("#parts-search").focus()
    v.page.keyboard.press("ArrowLeft")
    v.page.keyboard.press("-")
    np.testing.assert_allclose(camera()["eye"], before["eye"], rtol=0)
    v.wait_final(n, v.js("window.vastray.seq"))
    assert not v.errors_received()


def test_the_wheel_zooms_towards_the_cursor(open_viewer: Any, server: Any, model: dict[str, Any]) -> None:
    """The wheel zooms about the point at the target's depth under the cursor: that point
    stays under the cursor, the view keeps its direction, and the eye comes nearer by the
    wheel's factor (1.0015 per pixel of scroll), in both projections."""
    v = open_viewer(server.open_url)
    n = v.wait_final()
    for projection in ("perspective", "orthographic"):
        if projection == "orthographic":
            v.page.click("#projection")
            n = v.wait_final(n, v.js("window.vastray.seq"))
        box = v.page.locator("#view").bounding_box()
        assert box is not None
        # (on whole page pixels: the wheel event's clientX and clientY are whole numbers)
        x = round(box["x"] + 0.25 * box["width"]) - box["x"]
        y = round(box["y"] + 0.3 * box["height"]) - box["y"]
        before = v.js(
            """([x, y, w, h]) => { const c = window.vastray.camera;
                return {point: c.pointAt(x, y, w, h), eye: c.eye, target: c.target}; }""",
            [x, y, box["width"], box["height"]],
        )
        v.page.mouse.move(box["x"] + x, box["y"] + y)
        v.page.mouse.wheel(0, -300)
        n = v.wait_final(n, v.js("window.vastray.seq"))
        after = v.js(
            """([p, w, h]) => { const c = window.vastray.camera;
                return {at: c.project(p, w, h), eye: c.eye, target: c.target}; }""",
            [before["point"], box["width"], box["height"]],
        )
        assert abs(after["at"]["x"] - x) < 0.01 and abs(after["at"]["y"] - y) < 0.01, after["at"]
        view = lambda c: np.subtract(c["target"], c["eye"])  # noqa: E731
        np.testing.assert_allclose(view(after), view(before) * 1.0015**-300, rtol=1e-9)
    assert not v.errors_received()


def test_a_double_click_turns_the_view_to_a_point(
    open_viewer: Any, server: Any, api: Any, model: dict[str, Any]
) -> None:
    """A double click turns the view to the full-detail point under it (the eye stays, so
    the centre ray meets the same point), and leaves no measurement behind (its first
    press, a click, is taken back);
    an orthographic view slides over instead (it keeps its direction); a click still
    picks at once; a double click on nothing says so."""
    v = open_viewer(server.open_url)
    n = v.wait_final()
    size = float(np.linalg.norm(np.subtract(model["bounds"][1], model["bounds"][0])))
    for projection in ("perspective", "orthographic"):
        if projection == "orthographic":
            v.page.click("#projection")
            n = v.wait_final(n, v.js("window.vastray.seq"))
        shown = v.shown()
        points = grid(shown, 9, 7, margin=0.25)
        hits = pick(api, model["id"], shown, points)
        # A hit away from the centre, so that the view has to turn.
        x, y = max(
            (p for p, h in zip(points, hits, strict=True) if h["hit"]),
            key=lambda p: np.hypot(p[0] - shown["width"] / 2, p[1] - shown["height"] / 2),
        )
        before = shown["camera"]
        sends = len(v.sent)
        v.page.mouse.dblclick(*v.page_point(x, y))
        v.wait_for("() => !window.vastray.picking.size")
        # Its first press was a click, which picked at once; the double click takes it back
        # (below: no measurement) and picks again to turn to the point.
        asked = [m for m in v.sent[sends:] if m["type"] == "pick"]
        assert len(asked) == 2, asked
        m = asked[-1]
        asked_view = {**shown, "camera": m["camera"], "width": m["width"], "height": m["height"]}
        point = pick(api, model["id"], asked_view, m["points"])[0]["position"]
        v.wait_for(
            "([p, tol]) => Math.hypot(...window.vastray.camera.target.map((v, i) => v - p[i])) < tol",
            [point, 1e-9 * size],
        )
        n = v.wait_final(n, v.js("window.vastray.seq"))
        after = v.shown()["camera"]
        np.testing.assert_allclose(after["target"], point, atol=1e-9 * size)
        if projection == "perspective":
            np.testing.assert_allclose(after["eye"], before["eye"], rtol=1e-12)
        else:
            offset = lambda c: np.subtract(c["eye"], c["target"])  # noqa: E731
            np.testing.assert_allclose(offset(after), offset(before), atol=1e-9 * size)
        w, h = v.shown()["width"], v.shown()["height"]
        centre = v.stream_pick([(w / 2, h / 2)])[0]
        assert centre["hit"], projection
        assert np.linalg.norm(np.subtract(centre["position"], point)) < 1e-3 * size, projection
        assert v.js("window.vastray.picks.length") == 0
        assert v.page.locator("#pick").inner_text().startswith("Click")
    # A click still picks.
    v.click_image(v.shown()["width"] / 2, v.shown()["height"] / 2)
    v.wait_for("() => document.getElementById('pick').innerText.startsWith('point:')")
    v.page.mouse.dblclick(*v.page_point(2.5, 2.5))
    v.wait_for("() => document.body.innerText.includes('Nothing there to turn to')")
    assert not v.errors_received()


def test_a_screenshot_downloads_the_finished_view(
    open_viewer: Any, server: Any, api: Any, model: dict[str, Any], artifacts: Any, request: Any
) -> None:
    v = open_viewer(server.open_url)
    v.wait_final()
    size = v.shown()
    with v.page.expect_download(timeout=60_000) as download:
        v.page.locator("#screenshot-button").click()
    path = artifacts / f"{request.node.name}-download.png"
    download.value.save_as(path)
    assert download.value.suggested_filename.startswith("vastray-plant-")
    image = Image.open(path)
    assert image.format == "PNG" and image.size == (size["width"], size["height"])
    plain = np.asarray(image.convert("RGB"), dtype=int)
    assert not_blank(plain)
    # With a measurement on the view, the screenshot has its marks burnt in: the markers'
    # colour where the page draws them, and the view as it was away from the marks.
    points = grid(size, 9, 7)
    hits = [p for p, h in zip(points, pick(api, model["id"], size, points), strict=True) if h["hit"]]
    for k, (x, y) in enumerate((hits[0], hits[-1])):
        v.click_image(x, y)
        v.wait_for("(k) => window.vastray.picks.length === k", k + 1)
    assert v.page.locator("#overlay circle.marker").count() == 2
    with v.page.expect_download(timeout=60_000) as download:
        v.page.locator("#screenshot-button").click()
    path = artifacts / f"{request.node.name}-download-marked.png"
    download.value.save_as(path)
    marked = np.asarray(Image.open(path).convert("RGB"), dtype=int)
    assert marked.shape == plain.shape
    fill = v.js("() => getComputedStyle(document.querySelector('#overlay circle.marker')).fill")
    accent = [int(c) for c in fill.removeprefix("rgb(").removesuffix(")").split(",")]
    for p in v.js("window.vastray.picks.map((p) => p.position)"):
        project = "([p, w, h]) => window.vastray.shown.camera.project(p, w, h)"
        at = v.js(project, [p, size["width"], size["height"]])
        x, y = int(at["x"]), int(at["y"])
        assert np.abs(marked[y, x] - accent).max() < 40, (marked[y, x], accent)
        assert np.abs(plain[y, x] - accent).max() >= 40
    changed = np.abs(marked - plain).sum(axis=-1) > 30
    assert 0 < changed.mean() < 0.05, changed.mean()
    assert "with the marks" in v.page.locator("body").inner_text()


def test_a_section_plane_hides_geometry(
    open_viewer: Any, server: Any, api: Any, model: dict[str, Any]
) -> None:
    """The '+ X' section cuts away x > the model's centre (docs: geometry where
    dot(normal, p) + offset < 0 is cut away): pixels whose first hit lay on the cut side
    change, pixels whose first hit lies on the kept side stay, and a pick through a
    cut-side point misses or hits deeper, on the kept side."""
    v = open_viewer(server.open_url)
    n = v.wait_final()
    shown = v.shown()
    lo, hi = (np.asarray(b) for b in model["bounds"])
    cut_x = float((lo[0] + hi[0]) / 2)
    margin = 0.02 * float(hi[0] - lo[0])
    # Sample points well inside surfaces: the point and its neighbours 2 pixels away
    # all hit on the same side of the plane, away from it.
    centres = grid(shown, 16, 10)
    offsets = [(0, 0), (2, 0), (-2, 0), (0, 2), (0, -2)]
    rays = [(x + dx, y + dy) for x, y in centres for dx, dy in offsets]
    hits = pick(api, model["id"], shown, rays)
    cut, kept = [], []
    for i, p in enumerate(centres):
        around = hits[5 * i : 5 * i + 5]
        if not all(h["hit"] for h in around):
            continue
        xs = [h["position"][0] for h in around]
        if min(xs) > cut_x + margin:
            cut.append(p)
        elif max(xs) < cut_x - margin:
            kept.append(p)
    assert len(cut) >= 5 and len(kept) >= 5, (len(cut), len(kept))
    before_cut, before_kept = v.pixels_at(cut), v.pixels_at(kept)

    page = v.page
    page.locator("#sections-panel summary").click()
    page.get_by_role("button", name="add a section plane across X").click()
    v.wait_for("() => window.vastray.panels.sections.length === 1")
    sent = [m for m in v.sent if m["type"] == "sections"]
    assert sent and sent[-1]["planes"][0]["normal"] == [-1, 0, 0]
    assert sent[-1]["planes"][0]["offset"] == pytest.approx(cut_x)
    v.wait_final(n)
    v.shot("sectioned")
    assert not v.errors_received(), v.errors_received()
    changed = lambda a, b: np.abs(a - b).sum(axis=-1) > 40  # noqa: E731
    # The kept side is as it was (a control: this holds with or without sections) ...
    assert changed(v.pixels_at(kept), before_kept).mean() < 0.2
    # ... rays through what lay on the cut side miss, or hit deeper, on the kept side ...
    tolerance = 1e-6 * float(np.abs(hi - lo).max())
    beyond = [h["position"] for h in v.stream_pick(cut) if h["hit"] and h["position"][0] > cut_x + tolerance]
    assert not beyond, f"{len(beyond)} of {len(cut)} picks hit cut-away geometry, e.g. {beyond[0]}"
    # ... and the picture shows it.
    assert changed(v.pixels_at(cut), before_cut).mean() > 0.5, "the section plane hid nothing"
    # A click on such a point says so too.
    v.click_image(*cut[len(cut) // 2])
    v.wait_for("() => !document.getElementById('pick').innerText.startsWith('Click')")
    if not page.locator("#pick").inner_text().startswith("Nothing there"):
        assert v.js("window.vastray.picks.at(-1).position")[0] <= cut_x + tolerance


def test_the_model_picker_switches_models(open_viewer: Any, server: Any, model: dict[str, Any]) -> None:
    other = build_model(server, "scene:spheres:3000:1", "spheres")
    try:
        v = open_viewer(f"{server.open_url}&model={model['id']}")
        n = v.wait_final()
        plant = v.thumbnail()
        select = v.page.locator("#model-select")
        assert select.locator("option").count() == 2
        select.select_option(other["id"])
        v.wait_for("(id) => window.vastray.model?.id === id", other["id"])
        v.wait_final(n)
        v.shot("spheres")
        assert f"model={other['id']}" in v.page.url
        assert np.abs(v.thumbnail() - plant).mean() > 8, "still the other model's picture"
    finally:
        with server.client() as api:  # the other tests open the server's URL: one model there
            api.delete(f"/api/models/{other['id']}")


def test_clear_messages_for_a_wrong_key_and_a_missing_model(open_viewer: Any, server: Any) -> None:
    wrong = open_viewer(f"{server.url}/?key=not-the-key", "wrong-key")
    wrong.wait_for("() => !document.getElementById('banner').hidden")
    text = wrong.page.locator("#banner").inner_text()
    assert text.startswith("Access refused") and "URL the server printed" in text, text
    assert wrong.page.locator("#status").get_attribute("data-state") == "failed"
    gone = open_viewer(f"{server.open_url}&model=mdl-000000000000", "missing-model")
    gone.wait_for("() => document.getElementById('status').dataset.state === 'failed'")
    text = gone.page.locator("#banner").inner_text()
    assert "model is gone" in text and "mdl-000000000000" in text, text


def delete_all_but(server: Any, model: dict[str, Any]) -> None:
    """Deletes the models a test added: the other tests open the server's URL, which
    shows its one model."""
    with server.client() as api:
        for m in api.get("/api/models").json():
            if m["id"] != model["id"]:
                api.delete(f"/api/models/{m['id']}")


def drop_file(v: Any, path: Path) -> None:
    """Drops the file on the stage, as a user drags it from the desktop."""
    v.js(
        """([name, b64]) => {
            const bytes = Uint8Array.from(atob(b64), (c) => c.charCodeAt(0));
            const data = new DataTransfer();
            data.items.add(new File([bytes], name));
            const stage = document.getElementById('stage');
            const drag = {dataTransfer: data, bubbles: true, cancelable: true};
            stage.dispatchEvent(new DragEvent('dragover', drag));
            stage.dispatchEvent(new DragEvent('drop', drag));
        }""",
        [path.name, base64.b64encode(path.read_bytes()).decode()],
    )


def test_a_dropped_mesh_is_uploaded_built_and_shown(
    open_viewer: Any, server: Any, model: dict[str, Any], tmp_path: Path
) -> None:
    mesh = tmp_path / "balls.ply"
    subprocess.run(
        [VASTRAY, "scene", "spheres", "--triangles", "3000", "--seed", "2", "-o", mesh], check=True
    )
    v = open_viewer(f"{server.open_url}&model={model['id']}")
    n = v.wait_final()
    v.js(
        """() => {
            const label = document.getElementById('job-label');
            window.__job = [];
            new MutationObserver(() => window.__job.push(label.textContent))
                .observe(label, {childList: true, characterData: true, subtree: true});
        }"""
    )
    drop_file(v, mesh)
    try:
        v.wait_for("() => window.vastray.model?.name === 'balls'")
        v.wait_final(n)
        v.shot("built")
        labels = v.js("window.__job")
        assert any(t.startswith("uploading balls.ply") for t in labels), labels
        assert any(t.startswith("balls:") for t in labels), labels  # the build's live progress
        assert v.page.locator("#job").is_hidden() and v.page.locator("#drop-hint").is_hidden()
        assert "balls (3,0" in v.page.locator("#model-select option:checked").inner_text()
        assert not_blank(v.thumbnail())
    finally:
        delete_all_but(server, model)


def test_an_upload_builds_with_the_chosen_layout(
    open_viewer: Any, server: Any, model: dict[str, Any], tmp_path: Path
) -> None:
    """The upload's layout choice reaches the builder: "smallest files" builds the mesh
    untiered, with compact blocks, quantized vertices and a coarser tree, and the page
    shows the model it built."""
    mesh = tmp_path / "pipes.ply"
    subprocess.run([VASTRAY, "scene", "plant", "--triangles", "20000", "--seed", "3", "-o", mesh], check=True)
    v = open_viewer(f"{server.open_url}&model={model['id']}")
    v.wait_final()
    assert v.page.locator("#upload-layout").is_visible()
    v.page.select_option("#upload-layout", "smallest")
    drop_file(v, mesh)
    try:
        v.wait_for("() => window.vastray.model?.name === 'pipes'")
        v.wait_final()
        with server.client() as api:
            built = next(m for m in api.get("/api/models").json() if m["name"] == "pipes")
            options = api.get(f"/api/models/{built['id']}").json()["build"]["options"]
        assert options["compact_triangles"] is True and options["quantized_vertices"] is True
        assert options["tier_width"] == 0 and options["traversal_cost"] == 6 and options["lz4_hc_level"] == 9
        assert not_blank(v.thumbnail())
    finally:
        delete_all_but(server, model)
