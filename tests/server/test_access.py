"""Access control and limits: keys, viewing tokens (per model, expiring), paths outside
the data directory, oversized uploads and bodies, absurd render requests, request
rates. Every refusal is a 4xx with a message that says what to change, and the server
keeps serving."""

from __future__ import annotations

import math
import time
from pathlib import Path
from typing import Any

import httpx
import pytest
from serverproc import ServerProcess, error, wait_for_job


@pytest.fixture(scope="module")
def models(api: httpx.Client) -> tuple[str, str]:
    """Two small models."""
    ids = []
    for source in ("scene:spheres:4000:1", "scene:plant:8000:2"):
        job = api.post("/api/jobs", json={"source": source}).json()
        assert wait_for_job(api, job["id"])["state"] == "succeeded"
        ids.append(job["model_id"])
    return ids[0], ids[1]


def test_write_endpoints_need_the_key(server: ServerProcess, models: tuple[str, str]) -> None:
    a, _ = models
    with server.client(key=None) as anon, server.client(key="wrong-key-0123456789") as wrong:
        for client, status in ((anon, 401), (wrong, 401)):
            error(client.post("/api/jobs", json={"source": "demo"}), status, "unauthorized")
            error(client.delete(f"/api/models/{a}"), status)
            error(client.post("/api/uploads", params={"filename": "x.ply"}, content=b"ply"), status)
            error(client.get("/api/jobs"), status)
            error(client.post(f"/api/models/{a}/render", json={}), status)
        assert "API key" in error(anon.post("/api/jobs", json={"source": "demo"}), 401)
    # The key works in each of the accepted places.
    key = server.key
    assert httpx.get(f"{server.url}/api/jobs", headers={"X-API-Key": key}).status_code == 200
    assert httpx.get(f"{server.url}/api/jobs", params={"key": key}).status_code == 200


def test_viewing_tokens(server: ServerProcess, api: httpx.Client, models: tuple[str, str]) -> None:
    a, b = models
    r = api.post(f"/api/models/{a}/tokens", json={"ttl_seconds": 600, "label": "review link"})
    assert r.status_code == 201
    token = r.json()["token"]
    assert r.json()["subject"] == a and r.json()["expires_at"] > time.time()
    with server.client(key=token) as viewer:
        assert (
            viewer.post(f"/api/models/{a}/render", json={"camera": {"width": 16, "height": 16}}).status_code
            == 200
        )
        assert [m["id"] for m in viewer.get("/api/models").json()] == [a]
        assert viewer.get(f"/api/models/{a}").status_code == 200
        assert "does not grant access" in error(
            viewer.post(f"/api/models/{b}/render", json={}), 403, "forbidden"
        )
        assert "only views" in error(viewer.post("/api/jobs", json={"source": "demo"}), 403)
        error(viewer.delete(f"/api/models/{a}"), 403)
    # A wrong secret with a real id, and a malformed token.
    token_id = token.split("_")[1]
    for bad in (f"vt_{token_id}_{'x' * 32}", "vt_nonsense", token[:-1]):
        with server.client(key=bad) as c:
            error(c.post(f"/api/models/{a}/render", json={}), 401, "unauthorized")
    # Expired.
    short = api.post(f"/api/models/{a}/tokens", json={"ttl_seconds": 0.2}).json()["token"]
    time.sleep(0.4)
    with server.client(key=short) as c:
        assert "expired" in error(c.post(f"/api/models/{a}/render", json={}), 401, "token_expired")
    error(api.post(f"/api/models/{a}/tokens", json={"ttl_seconds": -1}), 422)
    error(api.post("/api/models/mdl-nosuch/tokens", json={}), 404, "model_not_found")


def test_paths_outside_the_data_directory(server: ServerProcess, api: httpx.Client, tmp_path: Path) -> None:
    outside = tmp_path / "secret.vast"
    outside.write_bytes(b"not yours")
    (server.data_dir / "escape.vast").unlink(missing_ok=True)
    (server.data_dir / "escape.vast").symlink_to(outside)
    for path in (
        "../secret.vast",
        "/etc/passwd",
        str(outside),
        "escape.vast",
        "a/../../secret.vast",
        "models/../../secret.vast",
        "registry.sqlite3/../../x",
    ):
        msg = error(api.post("/api/models", json={"path": path}), 403, "path_outside_data")
        assert "data directory" in msg
    msg = error(api.post("/api/models", json={"path": "models/whatever.vast"}), 403)
    assert "manages" in msg
    error(api.post("/api/models", json={"path": "nothing-here.vast"}), 404, "file_not_found")
    (server.data_dir / "fake.vast").write_bytes(b"\0" * 300)
    assert "magic" in error(api.post("/api/models", json={"path": "fake.vast"}), 422, "invalid_model")


def test_oversized_uploads_are_refused(tmp_path: Path) -> None:
    s = ServerProcess(tmp_path / "data", "--no-demo", "--upload-limit", "1M").start()
    try:
        with s.client() as api:
            # Declared too big: refused before the body is read.
            r = api.post("/api/uploads", params={"filename": "big.ply"}, content=b"x" * (2 << 20))
            assert "at most 1.0 MiB" in error(r, 413, "upload_too_large")

            # Too big without a length: refused when the limit is passed, the part removed.
            def chunks() -> Any:
                for _ in range(40):
                    yield b"y" * (64 << 10)

            r = api.post("/api/uploads", params={"filename": "big.ply"}, content=chunks())
            error(r, 413, "upload_too_large")
            uploads = s.data_dir / "uploads"
            assert not any(uploads.iterdir()), list(uploads.iterdir())
            error(
                api.post("/api/uploads", params={"filename": "empty.ply"}, content=b""), 400, "empty_upload"
            )
            error(api.post("/api/uploads", params={"filename": "x.exe"}, content=b"MZ"), 415)
            assert not any(uploads.iterdir())
            # The server still takes what fits.
            r = api.post("/api/uploads", params={"filename": "small.stl"}, content=b"z" * 1000)
            assert r.status_code == 201 and r.json()["kind"] == "mesh"
            # And JSON bodies are capped too.
            r = api.post(
                "/api/jobs",
                content=b"{" + b" " * (2 << 20) + b"}",
                headers={"content-type": "application/json"},
            )
            error(r, 413, "request_too_large")
    finally:
        s.stop()


@pytest.mark.parametrize(
    ("camera", "message"),
    [
        ({"eye": [math.nan, 0, 0]}, "finite"),
        ({"eye": [1, 2, 3], "target": [1, 2, 3]}, "zero length"),
        ({"up": [0, 0, 0]}, "up vector"),
        ({"eye": [0, 10, 0], "target": [0, 0, 0], "up": [0, 1, 0]}, "parallel"),
        ({"fov": 0}, "fov"),
        ({"fov": 180}, "fov"),
        ({"fov": math.nan}, "fov: Input should be a finite number"),
        ({"fov": math.inf}, "fov: Input should be a finite number"),
        ({"width": 100_000, "height": 100_000}, "16384"),
        ({"width": 10_000, "height": 10_000}, "pixel budget"),
        ({"width": 0}, "width"),
        ({"zoom": 2}, "zoom"),
    ],
)
def test_absurd_render_requests(
    api: httpx.Client, models: tuple[str, str], camera: dict, message: str
) -> None:
    a, _ = models
    # json.dumps writes NaN as the bare literal NaN, as a careless client would send it.
    import json

    r = api.post(
        f"/api/models/{a}/render",
        content=json.dumps({"camera": camera}),
        headers={"content-type": "application/json"},
    )
    assert message in error(r, 422), r.json()
    r = api.post(
        f"/api/models/{a}/pick",
        content=json.dumps({"camera": camera, "points": [[1, 1]]}),
        headers={"content-type": "application/json"},
    )
    assert r.status_code == 422
    assert api.post(f"/api/models/{a}/render", json={"camera": {"width": 8, "height": 8}}).status_code == 200


def test_bad_quality_and_pick_requests(api: httpx.Client, models: tuple[str, str]) -> None:
    a, _ = models
    cases = [
        ({"quality": {"shading": "phong"}}, "shading"),
        ({"quality": {"pixels_of_error": -1}}, "pixels_of_error"),
        ({"quality": {"ao_samples": 0}}, "ao_samples"),
        ({"quality": {"sun_direction": [0, 0, 0]}}, "sun direction"),
        ({"format": "gif"}, "format"),
        ({"timeout": 0}, "timeout"),
        ({"timeout": 10_000}, "timeout"),
    ]
    for body, message in cases:
        assert message in error(api.post(f"/api/models/{a}/render", json=body), 422), body
    for body, message in [
        ({"points": [[1, 1]]}, "camera"),
        ({}, "points"),
        ({"rays": [[[0, 0, 0], [0, 0, 0]]]}, "zero-length"),
        ({"rays": [[[0, 0, 0], [0, 0, 1]]] * 5000}, "4096"),
    ]:
        assert message in error(api.post(f"/api/models/{a}/pick", json=body), 422), body
    error(api.post("/api/models/mdl-nosuch/render", json={}), 404, "model_not_found")


def test_request_rate_is_limited_per_client(tmp_path: Path) -> None:
    s = ServerProcess(tmp_path / "data", "--no-demo", env={"VASTRAY_REQUEST_RATE": "2"}).start()
    try:
        with s.client() as api:
            job = api.post("/api/jobs", json={"source": "scene:spheres:1000:1"}).json()
            wait_for_job(api, job["id"])
            statuses = [
                api.post(
                    f"/api/models/{job['model_id']}/pick", json={"rays": [[[0, 0, 9], [0, 0, -1]]]}
                ).status_code
                for _ in range(12)
            ]
            assert 429 in statuses and statuses[0] == 200
            r = api.post(f"/api/models/{job['model_id']}/pick", json={"rays": [[[0, 0, 9], [0, 0, -1]]]})
            if r.status_code == 429:
                assert int(r.headers["retry-after"]) >= 1 and "retry" in r.json()["error"]["message"]
            time.sleep(1.5)
            assert api.get("/readyz").status_code == 200  # other endpoints are not limited
    finally:
        s.stop()
