"""A z-up model in the page: it opens on its side; picking +Z in the up picker turns the
view upright at once, saves the setting with the model (the page holds the API key),
and after a reload the page opens it upright, showing what the y-up original shows."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import trimesh

from vastray import scenes
from vastray.build import BuildOptions, build_model

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
    finally:
        api.delete(f"/api/models/{y_id}")  # the other tests open the server's URL: one model there
        api.delete(f"/api/models/{z_id}")
