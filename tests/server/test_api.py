"""The REST API end to end against a real server: upload a mesh, watch its build to the
end over server-sent events, list and inspect the model, render it (decoded and
checked), pick it (the input's own triangle ids, checked against a double-precision
brute-force reference), register a model in place, health and metrics."""

from __future__ import annotations

import io
import json
import math
import shutil
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest
import trimesh
from PIL import Image
from serverproc import ServerProcess

from vastray import native, scenes
from vastray.build import BuildOptions, build_model

TRIANGLES = 40_000


def read_events(client: httpx.Client, url: str) -> list[tuple[str, dict[str, Any]]]:
    """Server-sent events of a job until its `end` event."""
    events = []
    with client.stream("GET", url, timeout=180) as r:
        assert r.status_code == 200 and r.headers["content-type"].startswith("text/event-stream")
        kind = None
        for line in r.iter_lines():
            if line.startswith("event: "):
                kind = line[7:]
            elif line.startswith("data: ") and kind is not None:
                events.append((kind, json.loads(line[6:])))
                if kind == "end":
                    break
    return events


@pytest.fixture(scope="module")
def plant_ply(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("meshes") / "held-out-plant.ply"
    scenes.write_scene("plant", TRIANGLES, 11, path)
    return path


@pytest.fixture(scope="module")
def uploaded(api: httpx.Client, plant_ply: Path) -> dict[str, Any]:
    """The plant uploaded and registered: its build job watched to the end."""
    with open(plant_ply, "rb") as f:
        r = api.post(
            "/api/uploads",
            params={"filename": plant_ply.name, "register": "true", "name": "plant"},
            content=f,
        )
    assert r.status_code == 201, r.text
    up = r.json()
    assert up["kind"] == "mesh" and up["bytes"] == plant_ply.stat().st_size
    created = up["created"]
    job = created["job"]
    assert created["model"]["state"] == "building" and job["state"] in ("queued", "running")
    events = read_events(api, f"/api/jobs/{job['id']}/events")
    return {"model": created["model"], "job": job, "events": events}


def test_upload_builds_with_progress_to_the_end(api: httpx.Client, uploaded: dict[str, Any]) -> None:
    events = uploaded["events"]
    kinds = [k for k, _ in events]
    assert kinds[-1] == "end" and kinds.count("end") == 1
    final = events[-1][1]
    assert final["state"] == "succeeded", final
    assert final["percent"] == 100.0 and final["report"]["triangles"] > 0.9 * TRIANGLES
    percents = [e["percent"] for k, e in events if k == "progress"]
    assert percents == sorted(percents), "progress went backwards"
    phases = {e["phase"] for k, e in events if k == "progress"}
    assert {"read", "build"} <= phases, phases
    assert any("phase build" in line for line in final["log_tail"])
    job = api.get(f"/api/jobs/{final['id']}").json()
    assert job["state"] == "succeeded" and job["finished_at"] >= job["started_at"]
    log = api.get(f"/api/jobs/{final['id']}/log").text
    assert "succeeded" in log and "started in worker process" in log


def test_model_is_listed_and_inspected(api: httpx.Client, uploaded: dict[str, Any], plant_ply: Path) -> None:
    model_id = uploaded["model"]["id"]
    listed = {m["id"]: m for m in api.get("/api/models").json()}
    assert listed[model_id]["state"] == "ready"
    info = api.get(f"/api/models/{model_id}").json()
    mesh = trimesh.load(plant_ply, process=False)
    assert info["name"] == "plant" and info["input_triangles"] == len(mesh.faces)
    assert info["triangles"] == len(mesh.faces) - info["degenerate"]
    lo, hi = np.asarray(info["bounds"])
    np.testing.assert_allclose(lo, mesh.bounds[0], rtol=0, atol=1e-4)
    np.testing.assert_allclose(hi, mesh.bounds[1], rtol=0, atol=1e-4)
    assert info["lod_levels"] >= 3 and info["bytes"] > 0 and info["colours"] is True
    assert info["levels"][0]["level"] == 0 and info["levels"][-1]["level"] == "triangles"
    assert (
        info["build"]["options"]["memory"] > 0 and info["build"]["report"]["triangles"] == info["triangles"]
    )
    assert info["part_ids"] is False


def render(api: httpx.Client, model_id: str, **body: Any) -> tuple[np.ndarray, httpx.Response]:
    r = api.post(f"/api/models/{model_id}/render", json=body)
    assert r.status_code == 200, r.text
    return np.asarray(Image.open(io.BytesIO(r.content)).convert("RGB")), r


def test_one_shot_render(api: httpx.Client, uploaded: dict[str, Any]) -> None:
    model_id = uploaded["model"]["id"]
    overview, r = render(api, model_id, camera={"width": 320, "height": 200}, quality={"shading": "sun"})
    assert overview.shape == (200, 320, 3) and r.headers["content-type"] == "image/png"
    assert r.headers["x-vastray-complete"] == "true"
    stats = json.loads(r.headers["x-vastray-stats"])
    assert (
        stats["complete"] and stats["primary_rays"] == 320 * 200 and stats["voxel_hits"] == 0
    )  # full detail
    background = overview[0, 0]
    assert (np.abs(overview.astype(int) - background).sum(axis=2) > 30).mean() > 0.1, "image is blank"
    info = api.get(f"/api/models/{model_id}").json()
    lo, hi = np.asarray(info["bounds"])
    centre = (lo + hi) / 2
    close, _ = render(
        api,
        model_id,
        camera={
            "eye": list(centre + (hi - lo) * [0.2, 0.3, 0.6]),
            "target": list(centre),
            "width": 320,
            "height": 200,
        },
    )
    assert np.abs(close.astype(int) - overview.astype(int)).mean() > 5, "another camera gave the same image"
    jpeg, r = render(api, model_id, camera={"width": 320, "height": 200}, format="jpeg", jpeg_quality=80)
    assert r.headers["content-type"] == "image/jpeg" and jpeg.shape == overview.shape
    # LOD renders are a choice: a coarse PoE is complete with voxels in it.
    _, r = render(api, model_id, camera={"width": 320, "height": 200}, quality={"pixels_of_error": 16})
    assert json.loads(r.headers["x-vastray-stats"])["voxel_hits"] > 0


def test_pick_names_the_input_triangles(api: httpx.Client, uploaded: dict[str, Any], plant_ply: Path) -> None:
    model_id = uploaded["model"]["id"]
    info = api.get(f"/api/models/{model_id}").json()
    lo, hi = np.asarray(info["bounds"])
    rng = np.random.default_rng(5)
    eye = (lo + hi) / 2 + (hi - lo) * [1.1, 0.9, 1.3]
    targets = lo + rng.random((300, 3)) * (hi - lo)
    directions = targets - eye
    rays = [[list(eye), list(d)] for d in directions]
    r = api.post(f"/api/models/{model_id}/pick", json={"rays": rays})
    assert r.status_code == 200, r.text
    hits = r.json()["hits"]
    mesh = trimesh.load(plant_ply, process=False)
    vertices, faces = np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces, dtype=np.uint32)
    origins = np.tile(eye, (len(directions), 1))
    ref = native.reference_intersect(vertices, faces, origins, directions)
    found = np.array([h["hit"] for h in hits])
    assert all(h["complete"] for h in hits)
    assert found.sum() > 50
    np.testing.assert_array_equal(found, ref["prim"] >= 0)
    ours = np.array([h["triangle"] if h["hit"] else -1 for h in hits])
    length = np.linalg.norm(directions, axis=1)
    with np.errstate(invalid="ignore"):  # inf - inf where a ray hits nothing
        tie = (ref["t_second"] - ref["t"]) * length <= 1e-4 * np.linalg.norm(hi - lo)
    same = (ours == ref["prim"]) | ~found
    assert (same | tie).all(), f"{(~(same | tie)).sum()} picks name another triangle"
    for h, t, d in zip(hits, ref["t"], length, strict=True):
        if h["hit"]:
            assert math.isclose(h["distance"], t * d, rel_tol=1e-5, abs_tol=1e-5)
            assert math.isclose(np.linalg.norm(h["normal"]), 1.0, rel_tol=1e-5)
    # Image points of a camera: the centre of the overview hits the plant.
    r = api.post(
        f"/api/models/{model_id}/pick",
        json={"camera": {"width": 320, "height": 200}, "points": [[160, 100], [0.5, 0.5]]},
    )
    centre, corner = r.json()["hits"]
    assert centre["hit"] and not corner["hit"]


def test_register_a_model_in_place(server: ServerProcess, api: httpx.Client, tmp_path: Path) -> None:
    """A built model copied into the data directory is served where it is; deleting the
    model forgets it and leaves the user's file."""
    folder = server.data_dir / "mine"
    folder.mkdir(exist_ok=True)
    path = folder / "spheres.vast"
    build_model("scene:spheres:5000:2", path, BuildOptions(memory=64 << 20))
    r = api.post("/api/models", json={"path": "mine/spheres.vast", "name": "spheres"})
    assert r.status_code == 201, r.text
    model = r.json()["model"]
    assert model["state"] == "ready" and model["file"] == "mine/spheres.vast" and r.json()["job"] is None
    image, _ = render(api, model["id"], camera={"width": 64, "height": 48})
    assert image.shape == (48, 64, 3)
    assert api.delete(f"/api/models/{model['id']}").status_code == 204
    assert path.is_file()
    assert api.get(f"/api/models/{model['id']}").status_code == 404
    # A mesh in the data directory starts a build (202).
    shutil.copyfile(Path(__file__).resolve().parents[2] / "README.md", folder / "notes.txt")  # any text
    r = api.post("/api/models", json={"path": "mine/notes.txt"})
    assert r.status_code == 415 and "unsupported file type" in r.json()["error"]["message"]


def test_health_and_metrics(server: ServerProcess, api: httpx.Client, uploaded: dict[str, Any]) -> None:
    assert httpx.get(f"{server.url}/healthz").json() == {"status": "ok"}
    ready = httpx.get(f"{server.url}/readyz").json()
    assert ready["status"] == "ready" and ready["models_ready"] >= 1 and ready["registry_schema"] >= 1
    render(api, uploaded["model"]["id"], camera={"width": 32, "height": 32})
    text = httpx.get(f"{server.url}/metrics").text
    for name in (
        "vastray_frames_total",
        "vastray_frame_seconds_bucket",
        "vastray_input_to_frame_seconds_bucket",
        "vastray_bytes_sent_total",
        "vastray_cache_hit_ratio",
        "vastray_working_set_bytes",
        "vastray_cache_bytes_loaded_total",
        'vastray_jobs{state="succeeded"}',
    ):
        assert name in text, name
    frames = [line for line in text.splitlines() if line.startswith('vastray_frames_total{kind="oneshot"}')]
    assert float(frames[0].split()[-1]) >= 1
    loaded = [line for line in text.splitlines() if line.startswith("vastray_cache_bytes_loaded_total")]
    assert float(loaded[0].split()[-1]) > 0
    assert httpx.get(f"{server.url}/openapi.json").json()["info"]["title"] == "vastray"
