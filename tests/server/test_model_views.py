"""Views saved with a model (/api/models/{id}/views), against a real server and its
SQLite registry: saved with the API key, listed for anyone who may view the model (a
viewing token too, which may not save or delete), refused with the field named when
bad (and nothing saved), at most MAX_VIEWS_PER_MODEL of them, announced to live views
of the model, gone with the model, kept across a restart; the Python client saves one
and a live view goes to it."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest
from serverproc import ServerProcess, error

from vastray.build import BuildOptions, build_model
from vastray.client import Client, VastrayError
from vastray.schemas import section_box

CAMERA = {"eye": [30.0, 20.0, 30.0], "target": [0.0, 2.0, 0.0], "up": [0.0, 1.0, 0.0], "fov": 40.0}


def register(server: ServerProcess, api: httpx.Client, name: str) -> str:
    build_model("scene:plant:5000:3", server.data_dir / f"{name}.vast", BuildOptions(memory=64 << 20))
    r = api.post("/api/models", json={"path": f"{name}.vast", "name": name})
    assert r.status_code == 201, r.text
    return str(r.json()["model"]["id"])


def test_views_are_saved_listed_and_deleted(server: ServerProcess, api: httpx.Client) -> None:
    model = register(server, api, "views")
    planes = [p.model_dump() for p in section_box((-5, 0, -5), (5, 4, 5))]
    body = {"name": "pump room", "camera": {**CAMERA, "seq": 17}, "sections": planes, "highlight": [3, 1]}
    r = api.post(f"/api/models/{model}/views", json=body)
    assert r.status_code == 201, r.text
    saved = r.json()
    assert saved["id"].startswith("view-") and saved["name"] == "pump room" and saved["highlight"] == [3, 1]
    assert saved["camera"]["seq"] == 0 and saved["camera"]["projection"] == "perspective"
    np.testing.assert_allclose(saved["camera"]["eye"], CAMERA["eye"])
    assert [p["offset"] for p in saved["sections"]] == [p["offset"] for p in planes]
    second = api.post(f"/api/models/{model}/views", json={"name": "top", "camera": CAMERA}).json()
    listed = api.get(f"/api/models/{model}/views").json()["views"]
    assert [v["id"] for v in listed] == [saved["id"], second["id"]]

    # A viewing token lists them, and may not save or delete.
    token = api.post(f"/api/models/{model}/tokens", json={"ttl_seconds": 600}).json()["token"]
    with httpx.Client(base_url=server.url, headers={"Authorization": f"Bearer {token}"}) as viewer:
        assert len(viewer.get(f"/api/models/{model}/views").json()["views"]) == 2
        error(viewer.post(f"/api/models/{model}/views", json=body), 403, "forbidden")
        error(viewer.delete(f"/api/models/{model}/views/{saved['id']}"), 403, "forbidden")

    assert api.delete(f"/api/models/{model}/views/{saved['id']}").status_code == 204
    error(api.delete(f"/api/models/{model}/views/{saved['id']}"), 404, "view_not_found")
    assert [v["name"] for v in api.get(f"/api/models/{model}/views").json()["views"]] == ["top"]


def test_live_views_of_the_model_hear_of_saved_and_deleted_views(
    server: ServerProcess, api: httpx.Client
) -> None:
    """A `model_views` event reaches every stream viewing the model (the page lists its
    views again), and not the streams of other models."""
    model, other = register(server, api, "heard"), register(server, api, "not-heard")

    def heard(view: Any, count: int) -> None:
        deadline = time.monotonic() + 30
        while sum(e.get("type") == "model_views" for e in view.events) < count:
            assert time.monotonic() < deadline, view.events
            time.sleep(0.02)

    with Client(server.open_url) as vr, vr.view(model) as watching, vr.view(other) as elsewhere:
        watching.next_frame()
        elsewhere.next_frame()
        saved = api.post(f"/api/models/{model}/views", json={"name": "v", "camera": CAMERA}).json()
        heard(watching, 1)
        news = [e for e in watching.events if e["type"] == "model_views"]
        assert news == [{"type": "model_views", "model": model}]
        api.delete(f"/api/models/{model}/views/{saved['id']}").raise_for_status()
        heard(watching, 2)
        assert not any(e.get("type") == "model_views" for e in elsewhere.events)


def test_bad_views_are_refused_and_nothing_is_saved(server: ServerProcess, api: httpx.Client) -> None:
    model = register(server, api, "bad-views")
    base = {"name": "v", "camera": CAMERA}
    cases = [
        ({**base, "name": ""}, 422, "name"),
        ({**base, "camera": {**CAMERA, "target": CAMERA["eye"]}}, 422, "camera"),  # eye on the target
        ({**base, "camera": {**CAMERA, "fov": 180}}, 422, "fov"),
        ({**base, "sections": [{"normal": [0, 0, 0], "offset": 1}]}, 422, "normal"),
        ({**base, "sections": [{"normal": [1, 0, 0], "offset": 0}] * 7}, 422, "sections"),
        ({**base, "colour": "red"}, 422, "colour"),
    ]
    for body, status, named in cases:
        message = error(api.post(f"/api/models/{model}/views", json=body), status)
        assert named in message, (named, message)
    missing = "/api/models/mdl-nosuchmodel/views"
    error(api.get(missing), 404, "model_not_found")
    error(api.post(missing, json=base), 404, "model_not_found")
    assert api.get(f"/api/models/{model}/views").json()["views"] == []


def test_a_model_keeps_at_most_so_many_views(server: ServerProcess, api: httpx.Client) -> None:
    from vastray.server.routes.model_views import MAX_VIEWS_PER_MODEL

    model = register(server, api, "many-views")
    for k in range(MAX_VIEWS_PER_MODEL):
        r = api.post(f"/api/models/{model}/views", json={"name": f"v{k}", "camera": CAMERA})
        assert r.status_code == 201, r.text
    r = api.post(f"/api/models/{model}/views", json={"name": "one more", "camera": CAMERA})
    error(r, 409, "too_many_views")
    assert len(api.get(f"/api/models/{model}/views").json()["views"]) == MAX_VIEWS_PER_MODEL


def test_views_go_with_their_model(server: ServerProcess, api: httpx.Client) -> None:
    model = register(server, api, "doomed")
    api.post(f"/api/models/{model}/views", json={"name": "v", "camera": CAMERA}).raise_for_status()
    assert api.delete(f"/api/models/{model}").status_code == 204
    error(api.get(f"/api/models/{model}/views"), 404, "model_not_found")
    from vastray.server.registry import Registry

    registry = Registry(server.data_dir)
    try:
        assert registry.model_views(model) == []
    finally:
        registry.close()


def test_the_client_saves_a_view_that_a_live_view_goes_to_after_a_restart(tmp_path: Path) -> None:
    s = ServerProcess(tmp_path / "data", "--no-demo").start()
    try:
        with s.client() as api:
            model = register(s, api, "kept")
        box = section_box((-4, 0, -4), (4, 3, 4))
        with Client(s.open_url) as vr:
            saved = vr.save_model_view(model, "middle", camera=CAMERA, sections=box, highlight=[2])
        s.stop()
        s.start()
        with Client(s.open_url) as vr:
            (again,) = vr.model_views(model)
            assert again == saved
            # Where the saved view's box shows something, and where the whole model does
            # outside the box (REST picks of the same camera): the live view shows the box.
            camera = {**CAMERA, "width": 160, "height": 120}
            grid = [(x + 0.5, y + 0.5) for y in range(0, 120, 3) for x in range(0, 160, 3)]
            boxed = vr.pick(model, points=grid, camera=camera, sections=box)
            whole = vr.pick(model, points=grid, camera=camera)
            inside = [i for i, h in enumerate(boxed) if h.hit][:32]
            outside = [i for i, h in enumerate(whole) if h.hit and abs(h.position[0]) > 4.5][:32]
            assert len(inside) >= 5 and len(outside) >= 5, (len(inside), len(outside))
            chosen = inside + outside
            with vr.view(model, viewport=(160, 120)) as view:
                view.final(view.show(again))
                assert view.camera is not None and view.camera.fov == 40.0
                np.testing.assert_allclose(view.camera.eye, CAMERA["eye"])
                shown = view.pick([grid[i] for i in chosen])
                assert [h.triangle for h in shown] == [boxed[i].triangle for i in chosen]
            vr.delete_model_view(model, again["id"])
            assert vr.model_views(model) == []
            with pytest.raises(VastrayError) as err:
                vr.delete_model_view(model, again["id"])
            assert err.value.status == 404
    finally:
        s.stop()
