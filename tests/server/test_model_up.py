"""Which way is up in a model: a z-up copy of a y-up mesh opens on its side until an
admin says `up` is +z (PATCH /api/models/{id}); then its default views (one-shot
renders, a stream's welcome) are the y-up original's turned with it, and the setting
outlives a restart. Bad patches are refused and change nothing."""

from __future__ import annotations

import asyncio
import io
import json
import time
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest
import trimesh
import websockets
from PIL import Image
from serverproc import ServerProcess, wait_for_job

from vastray import scenes
from vastray.build import BuildOptions, build_model
from vastray.client import Client
from vastray.modelfile import ModelFile

pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning")

# The quarter turn about x that takes +y to +z: (x, y, z) -> (x, -z, y).
Y_TO_Z = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])


@pytest.fixture(scope="module")
def pair(
    server: ServerProcess, api: httpx.Client, tmp_path_factory: pytest.TempPathFactory
) -> dict[str, str]:
    """The plant as built (y-up) and the same plant turned to be z-up, registered."""
    meshes = tmp_path_factory.mktemp("meshes")
    upright = meshes / "plant.ply"
    scenes.write_scene("plant", 30_000, 4, upright)
    mesh = trimesh.load(upright, process=False)
    turned = mesh.copy()
    turned.vertices = np.asarray(mesh.vertices) @ Y_TO_Z.T
    turned.export(meshes / "plant-z.ply")
    ids = {}
    for name in ("plant", "plant-z"):
        target = server.data_dir / f"{name}.vast"
        build_model(str(meshes / f"{name}.ply"), target, BuildOptions(memory=64 << 20))
        r = api.post("/api/models", json={"path": target.name, "name": name})
        assert r.status_code == 201, r.text
        ids[name] = r.json()["model"]["id"]
    return ids


def overview(api: httpx.Client, model_id: str, **camera: Any) -> np.ndarray:
    r = api.post(
        f"/api/models/{model_id}/render",
        json={"camera": {"width": 240, "height": 160, **camera}, "quality": {"shading": "headlight"}},
    )
    assert r.status_code == 200, r.text
    return np.asarray(Image.open(io.BytesIO(r.content)).convert("RGB")).astype(int)


async def welcome(server: ServerProcess, model_id: str) -> dict[str, Any]:
    url = server.url.replace("http://", "ws://") + "/api/stream"
    async with websockets.connect(url, max_size=1 << 26) as ws:
        hello = {"type": "hello", "protocol": 1, "model": model_id, "token": server.key}
        await ws.send(json.dumps({**hello, "viewport": {"width": 320, "height": 180}}))
        while True:
            m = await asyncio.wait_for(ws.recv(), 30)
            if isinstance(m, str) and json.loads(m)["type"] == "welcome":
                return dict(json.loads(m))


def differing(a: np.ndarray, b: np.ndarray) -> float:
    """The share of pixels that differ visibly."""
    return float((np.abs(a - b).sum(axis=2) > 30).mean())


def test_a_z_up_model_opens_upright_once_it_says_so(
    server: ServerProcess, api: httpx.Client, pair: dict[str, str]
) -> None:
    y_id, z_id = pair["plant"], pair["plant-z"]
    assert api.get(f"/api/models/{z_id}").json()["up"] == [0.0, 1.0, 0.0]  # until told otherwise
    original = overview(api, y_id)
    assert differing(overview(api, z_id), original) > 0.2, "the z-up copy already looks like the original"

    r = api.patch(f"/api/models/{z_id}", json={"up": [0, 0, 2.5]})
    assert r.status_code == 200, r.text
    assert r.json()["up"] == [0.0, 0.0, 1.0]  # stored as a unit vector
    assert api.get(f"/api/models/{z_id}").json()["up"] == [0.0, 0.0, 1.0]

    # The default camera is now the original's turned by the same quarter turn, and a
    # headlight sees the turned world from it as the original from its own: the same
    # picture but for the odd pixel where the two trees split a tie differently.
    upright = overview(api, z_id)
    assert differing(upright, original) < 0.01, f"{differing(upright, original):.3f} of the pixels differ"

    # A stream's first view is the same: its camera's up is +z, the eye above and in
    # front (-y) of the model, just as the original's is above and in front (+z).
    w_y, w_z = asyncio.run(welcome(server, y_id)), asyncio.run(welcome(server, z_id))
    assert w_z["model"]["up"] == [0.0, 0.0, 1.0]
    cam_y, cam_z = w_y["camera"], w_z["camera"]
    assert cam_z["up"] == [0.0, 0.0, 1.0]
    for key in ("eye", "target"):
        np.testing.assert_allclose(cam_z[key], Y_TO_Z @ np.asarray(cam_y[key]), rtol=1e-6, atol=1e-6)

    # A request's own up still wins over the model's.
    assert differing(overview(api, z_id, up=[0.0, 1.0, 0.0]), original) > 0.2
    # The standard views turn with it too: the z-up copy's front and top are the original's.
    for view in ("front", "top"):
        side = overview(api, y_id, view=view)
        assert differing(side, original) > 0.2, f"the {view} view is the three-quarter one"
        assert differing(overview(api, z_id, view=view), side) < 0.01, view
    r = api.post(f"/api/models/{z_id}/render", json={"camera": {"view": "front", "eye": [1, 2, 3]}})
    assert r.status_code == 422 and "standard view" in r.json()["error"]["message"], r.text


def test_bad_patches_are_refused_and_change_nothing(
    server: ServerProcess, api: httpx.Client, pair: dict[str, str]
) -> None:
    model_id = pair["plant"]
    before = api.get(f"/api/models/{model_id}").json()
    for body, says in [
        ({"up": [0, 0, 0]}, "up: up vector has zero length"),
        ({"up": [0, 1]}, "up"),
        ({"upp": [0, 0, 1]}, "upp: Extra inputs are not permitted"),
        ({"name": ""}, "name"),
        ({"units": "furlong"}, "units: Input should be 'mm', 'cm', 'm', 'km', 'in', 'ft' or ''"),
        ({"units": 1}, "units"),
    ]:
        r = api.patch(f"/api/models/{model_id}", json=body)
        assert r.status_code == 422, (body, r.text)
        error = r.json()["error"]
        assert error["code"] == "invalid_request" and says in error["message"], (body, error)
    r = api.patch("/api/models/mdl_nothere", json={"up": [0, 0, 1]})
    assert r.status_code == 404 and r.json()["error"]["code"] == "model_not_found"
    assert httpx.patch(f"{server.url}/api/models/{model_id}", json={"up": [0, 0, 1]}).status_code == 401
    # A viewing token may look, not change.
    token = api.post(f"/api/models/{model_id}/tokens", json={}).json()["token"]
    r = httpx.patch(
        f"{server.url}/api/models/{model_id}",
        json={"up": [0, 0, 1]},
        headers={"Authorization": f"Bearer {token}"},
    )
    assert r.status_code in (401, 403), r.text
    after = api.get(f"/api/models/{model_id}").json()
    assert (after["up"], after["name"], after["units"]) == (before["up"], before["name"], before["units"])


def test_up_given_when_a_model_is_registered_uploaded_or_built(
    server: ServerProcess, api: httpx.Client, tmp_path: Path
) -> None:
    """A script that knows its mesh is z-up says so in the call that adds it; a build
    finishing later keeps it. A bad one is refused before anything is made."""
    build_model("scene:spheres:3000:2", server.data_dir / "in-place.vast", BuildOptions(memory=64 << 20))
    r = api.post("/api/models", json={"path": "in-place.vast", "up": [0, 0, 5]})
    assert r.status_code == 201 and r.json()["model"]["up"] == [0.0, 0.0, 1.0], r.text
    # A file that says which way is up (vastray build --up) is registered with it, unless
    # the request says otherwise.
    said = BuildOptions(memory=64 << 20, up=(1.0, 0.0, 0.0))
    build_model("scene:spheres:3000:2", server.data_dir / "x-up.vast", said)
    for body, up in [({}, [1.0, 0.0, 0.0]), ({"up": [0, -1, 0]}, [0.0, -1.0, 0.0])]:
        r = api.post("/api/models", json={"path": "x-up.vast", **body})
        assert r.status_code == 201 and r.json()["model"]["up"] == up, r.text

    mesh = tmp_path / "part.ply"
    scenes.write_scene("spheres", 2000, 3, mesh)
    models_before = {m["id"] for m in api.get("/api/models").json()}
    for up, register, says in [
        ("0,0,0", "true", "up: up vector has zero length"),
        ("z", "true", "up: expected three"),
        ("0,0,1", "false", "up goes with register=true"),
    ]:
        params = {"filename": "part.ply", "register": register, "up": up}
        r = api.post("/api/uploads", params=params, content=mesh.read_bytes())
        assert r.status_code == 422 and says in r.json()["error"]["message"], r.text
    assert {m["id"] for m in api.get("/api/models").json()} == models_before
    assert not any((server.data_dir / "uploads").glob("*")), "a refused upload left a file"

    r = api.post(
        "/api/uploads",
        params={"filename": "part.ply", "register": "true", "up": "0,0,1"},
        content=mesh.read_bytes(),
    )
    assert r.status_code == 201, r.text
    uploaded = r.json()["created"]
    assert uploaded["model"]["state"] == "building" and uploaded["model"]["up"] == [0.0, 0.0, 1.0]
    built = api.post("/api/jobs", json={"source": "scene:spheres:3000:4", "up": [-1, 0, 0]}).json()
    for job_id, model_id, up in [
        (uploaded["job"]["id"], uploaded["model"]["id"], [0.0, 0.0, 1.0]),
        (built["id"], built["model_id"], [-1.0, 0.0, 0.0]),
    ]:
        assert wait_for_job(api, job_id)["state"] == "succeeded"
        info = api.get(f"/api/models/{model_id}").json()
        assert info["state"] == "ready" and info["up"] == up, info
        with ModelFile(server.data_dir / info["file"]) as built:  # the file carries it too
            assert built.up == tuple(up)
    r = api.post("/api/jobs", json={"source": "scene:spheres:3000:4", "up": [0, 0, 0]})
    assert r.status_code == 422 and "up: up vector has zero length" in r.json()["error"]["message"]


def test_open_views_of_the_model_hear_a_patch(
    server: ServerProcess, api: httpx.Client, pair: dict[str, str]
) -> None:
    """A patch goes to every live view of the model as a `model` event (its name, up and
    units: a page shows them at once), and to no view of another model."""
    model, other = pair["plant"], pair["plant-z"]
    with Client(server.open_url) as vr, vr.view(model) as watching, vr.view(other) as elsewhere:
        watching.next_frame()
        elsewhere.next_frame()
        info = api.patch(f"/api/models/{model}", json={"units": "in"}).json()
        deadline = time.monotonic() + 30
        while not any(e.get("type") == "model" for e in watching.events):
            assert time.monotonic() < deadline, watching.events
            time.sleep(0.02)
        news = [e for e in watching.events if e["type"] == "model"]
        said = {"type": "model", "model": model, "name": info["name"], "up": info["up"], "units": "in"}
        assert news == [said]
        api.patch(f"/api/models/{model}", json={"units": ""}).raise_for_status()
        while sum(e.get("type") == "model" for e in watching.events) < 2:
            assert time.monotonic() < deadline, watching.events
            time.sleep(0.02)
        assert [e for e in watching.events if e["type"] == "model"][-1]["units"] is None
        assert not any(e.get("type") == "model" for e in elsewhere.events)


def test_up_name_and_units_outlive_a_restart(tmp_path: Path) -> None:
    s = ServerProcess(tmp_path / "data", "--no-demo").start()
    try:
        with s.client() as api:
            build_model("scene:spheres:3000:1", s.data_dir / "s.vast", BuildOptions(memory=64 << 20))
            model_id = api.post("/api/models", json={"path": "s.vast"}).json()["model"]["id"]
            assert api.get(f"/api/models/{model_id}").json()["units"] is None  # not said
            # (Any length will do: even one whose squares overflow a double.)
            r = api.patch(f"/api/models/{model_id}", json={"up": [-1e300, 0, 0], "name": "on its side"})
            assert r.status_code == 200 and r.json()["up"] == [-1.0, 0.0, 0.0], r.text
            r = api.patch(f"/api/models/{model_id}", json={"units": "mm"})
            assert r.status_code == 200 and r.json()["units"] == "mm" and r.json()["name"] == "on its side"
        s.stop()
        s.start()
        with s.client() as api:
            info = api.get(f"/api/models/{model_id}").json()
            assert info["up"] == [-1.0, 0.0, 0.0] and info["name"] == "on its side" and info["units"] == "mm"
            # The Python client says them too, and "" says none.
            with Client(s.url, key=s.key) as vr:
                assert vr.update_model(model_id, units="ft").units == "ft"
                assert vr.model(model_id).units == "ft"
                assert vr.update_model(model_id, units="").units is None
            assert api.get(f"/api/models/{model_id}").json()["units"] is None
    finally:
        s.stop()
