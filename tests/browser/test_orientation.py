"""Which way up the page shows a model. A z-up model opens on its side; picking +Z in
the up picker turns the view upright at once, saves the setting with the model (the
page holds the API key), and after a reload the page opens it upright, showing what the
y-up original shows. The standard views (buttons and keys 1-7) look at the named side,
upright about the model's up, framed as the server frames them; the projection button
(and O) switches to parallel rays and back, marks stay on what they mark, and W zooms a
parallel view."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import trimesh
from conftest import grid, not_blank, pick

from vastray import scenes
from vastray.build import BuildOptions, build_model
from vastray.camera import PROJECTIONS, STANDARD_VIEWS, frame_bounds

Y_TO_Z = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])  # +y to +z


def register(server: Any, api: Any, mesh: Path, name: str) -> str:
    target = server.data_dir / f"{name}.vast"
    build_model(str(mesh), target, BuildOptions(memory=64 << 20))
    r = api.post("/api/models", json={"path": target.name, "name": name})
    assert r.status_code == 201, r.text
    return str(r.json()["model"]["id"])


def test_the_up_picker_turns_the_view_and_saves_it(
    open_viewer: Any, server: Any, api: Any, tmp_path: Path
) -> None:
    upright = tmp_path / "plant.ply"
    scenes.write_scene("plant", 30_000, 4, upright)
    turned = trimesh.load(upright, process=False)
    turned.vertices = np.asarray(turned.vertices) @ Y_TO_Z.T
    turned.export(tmp_path / "plant-z.ply")
    y_id = register(server, api, upright, "plant-y")
    z_id = register(server, api, tmp_path / "plant-z.ply", "plant-z")
    try:
        original = open_viewer(f"{server.open_url}&model={y_id}", "original")
        original.wait_final()
        reference = original.thumbnail()

        v = open_viewer(f"{server.open_url}&model={z_id}")
        n = v.wait_final()
        v.shot("on-its-side")
        picker = v.page.locator("#model-up")
        assert picker.input_value() == "0,1,0"
        assert np.abs(v.thumbnail() - reference).mean() > 8, "the z-up copy already looks upright"

        picker.select_option("0,0,1")
        v.wait_for("() => window.vastray.camera?.up?.[2] === 1")
        v.wait_final(n, v.js("window.vastray.seq"))
        v.shot("upright")
        camera = v.shown()["camera"]
        assert camera["up"] == [0, 0, 1]
        # Framed from the front (-y) and above (+z), as a y-up model is from +z and above.
        assert camera["eye"][2] > camera["target"][2] and camera["eye"][1] < camera["target"][1]
        v.wait_for("() => /Saved with plant-z/.test(document.getElementById('banner').textContent)")
        assert api.get(f"/api/models/{z_id}").json()["up"] == [0.0, 0.0, 1.0]

        # Saved with the model: a new page opens it upright, with the original's picture.
        v.page.reload()
        v.wait_final()
        v.shot("reloaded")
        assert picker.input_value() == "0,0,1"
        assert v.shown()["camera"]["up"] == [0, 0, 1]
        assert np.abs(v.thumbnail() - reference).mean() < 3, "upright, yet not the original's picture"
        # Its front is now -y: the front view looks along +y, with +z up the screen.
        n = v.frames()
        v.page.click("#standard-views button[data-view=front]")
        v.wait_final(n, v.js("window.vastray.seq"))
        camera = v.shown()["camera"]
        np.testing.assert_allclose(direction(camera), [0, -1, 0], atol=1e-9)
        np.testing.assert_allclose(camera["up"], [0, 0, 1], atol=1e-9)
    finally:
        api.delete(f"/api/models/{y_id}")  # the other tests open the server's URL: one model there
        api.delete(f"/api/models/{z_id}")


def direction(camera: dict[str, Any]) -> np.ndarray:
    """Where the eye lies from the target, as a unit vector."""
    d = np.asarray(camera["eye"]) - np.asarray(camera["target"])
    return d / np.linalg.norm(d)


# Which way the eye lies from the model, and the screen's up, for a y-up model.
STANDARD = {
    "front": ([0, 0, 1], [0, 1, 0]),
    "right": ([1, 0, 0], [0, 1, 0]),
    "back": ([0, 0, -1], [0, 1, 0]),
    "left": ([-1, 0, 0], [0, 1, 0]),
    "top": ([0, 1, 0], [0, 0, -1]),  # the front at the bottom of the screen
    "bottom": ([0, -1, 0], [0, 0, 1]),
}


def test_standard_views_face_the_named_side(open_viewer: Any, server: Any, model: dict[str, Any]) -> None:
    v = open_viewer(server.open_url)
    n = v.wait_final()
    lo, hi = (np.asarray(b) for b in model["bounds"])
    before = v.thumbnail()
    for name, (side, up) in STANDARD.items():
        v.page.click(f"#standard-views button[data-view={name}]")
        n = v.wait_final(n, v.js("window.vastray.seq"))
        v.shot(name)
        camera = v.shown()["camera"]
        np.testing.assert_allclose(direction(camera), side, atol=1e-9, err_msg=name)
        np.testing.assert_allclose(camera["up"], up, atol=1e-9, err_msg=name)
        np.testing.assert_allclose(camera["target"], (lo + hi) / 2, rtol=1e-9, err_msg=name)
        shown = v.thumbnail()
        assert not_blank(shown), f"the {name} view shows nothing"
        assert np.abs(shown - before).mean() > 3, f"the {name} view looks like the one before it"
        before = shown
    # The keys: 1 is the three-quarter view the page opened with, 6 the top.
    v.page.locator("#view").focus()
    for key, side in [("6", STANDARD["top"][0]), ("1", [1, 0.7, 1.3] / np.linalg.norm([1, 0.7, 1.3]))]:
        v.page.keyboard.press(key)
        n = v.wait_final(n, v.js("window.vastray.seq"))
        np.testing.assert_allclose(direction(v.shown()["camera"]), side, atol=1e-9, err_msg=key)
    assert not v.errors_received()


def test_the_page_frames_a_view_as_the_server_does(
    open_viewer: Any, server: Any, model: dict[str, Any]
) -> None:
    """The page's framing (camera.js frameBounds: F, keys 1-7, the view a model opens
    with) is the server's (vastray.camera.frame_bounds, as REST renders with a `view`
    and the CLI frame): the same eye, target and up for every standard view, model up,
    projection and image shape, on a box of other proportions than the model's."""
    v = open_viewer(server.open_url)
    v.wait_final()
    lo, hi = (-3.0, 0.5, -1.0), (7.0, 2.0, 4.0)
    cases = [
        (name, up, projection, w, h)
        for name in STANDARD_VIEWS
        for up in ((0.0, 1.0, 0.0), (0.0, 0.0, 1.0), (1.0, 0.0, 0.0), (0.0, -1.0, 0.0))
        for projection in PROJECTIONS
        for w, h in ((1280, 720), (600, 900))
    ]
    framed = v.js(
        """async ([lo, hi, cases]) => {
            const { frameBounds } = await import('/ui/js/camera.js');
            return cases.map(([name, up, projection, w, h]) => {
                const c = frameBounds(lo, hi, 45, w / h, up, name, projection);
                return { eye: c.eye, target: c.target, up: c.up };
            });
        }""",
        [lo, hi, cases],
    )
    for (name, up, projection, w, h), page in zip(cases, framed, strict=True):
        server_side = frame_bounds(lo, hi, fov=45, width=w, height=h, up=up, view=name, projection=projection)
        case = str((name, up, projection, w, h))
        np.testing.assert_allclose(page["eye"], server_side.eye, rtol=1e-12, atol=1e-12, err_msg=case)
        np.testing.assert_allclose(page["target"], server_side.target, rtol=1e-12, atol=1e-12, err_msg=case)
        np.testing.assert_allclose(page["up"], server_side.up, atol=1e-12, err_msg=case)


def test_the_projection_button_switches_to_parallel_rays(
    open_viewer: Any, server: Any, api: Any, model: dict[str, Any]
) -> None:
    v = open_viewer(server.open_url)
    n = v.wait_final()
    button = v.page.locator("#projection")
    assert button.get_attribute("aria-pressed") == "false" and button.inner_text() == "Persp"
    before = v.thumbnail()
    button.click()
    n = v.wait_final(n, v.js("window.vastray.seq"))
    v.shot("orthographic")
    shown = v.shown()
    assert shown["camera"]["projection"] == "orthographic" and button.get_attribute("aria-pressed") == "true"
    parallel = v.thumbnail()
    assert not_blank(parallel) and np.abs(parallel - before).mean() > 2
    # A picked point is drawn where it was clicked: the page projects it along the same
    # parallel rays the server picked along.
    points = grid(shown, 7, 5, margin=0.3)
    hit = [p for p, h in zip(points, pick(api, model["id"], shown, points), strict=True) if h["hit"]]
    assert hit, "the model should fill the middle of the view"
    x, y = hit[len(hit) // 2]
    v.click_image(x, y)
    v.wait_for("() => document.getElementById('pick').innerText.startsWith('point:')")
    at = v.js(
        """([w, h]) => window.vastray.shown.camera.project(window.vastray.picks.at(-1).position, w, h)""",
        [shown["width"], shown["height"]],
    )
    assert abs(at["x"] - x) < 1.0 and abs(at["y"] - y) < 1.0, (at, x, y)
    # A standard view keeps the projection; O switches back.
    v.page.click("#standard-views button[data-view=front]")
    n = v.wait_final(n, v.js("window.vastray.seq"))
    front = v.shown()["camera"]
    assert front["projection"] == "orthographic"
    # W zooms an orthographic view (flying along parallel rays would show nothing new):
    # the eye comes nearer the target, which stays, and the picture changes.
    before = v.thumbnail()
    v.page.locator("#view").focus()
    v.page.keyboard.down("w")
    v.page.wait_for_timeout(500)
    v.page.keyboard.up("w")
    n = v.wait_final(n, v.js("window.vastray.seq"))
    zoomed = v.shown()["camera"]
    np.testing.assert_allclose(zoomed["target"], front["target"], rtol=1e-12)
    np.testing.assert_allclose(direction(zoomed), direction(front), atol=1e-9)
    distance = lambda c: np.linalg.norm(np.subtract(c["target"], c["eye"]))  # noqa: E731
    assert distance(zoomed) < 0.95 * distance(front)
    assert np.abs(v.thumbnail() - before).mean() > 2
    v.page.keyboard.press("o")
    v.wait_final(n, v.js("window.vastray.seq"))
    assert v.shown()["camera"]["projection"] == "perspective" and button.inner_text() == "Persp"
    assert not v.errors_received()
