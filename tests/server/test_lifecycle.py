"""The server's life: the demo built on first start while the API serves, restarts that
keep the registry (clean ones and crashes), jobs interrupted by either, deletes deferred
while a render uses the model, configuration from the environment, a registry from a
newer release refused."""

from __future__ import annotations

import logging
import signal
import socket
import sqlite3
import subprocess
import threading
import time
from pathlib import Path
from typing import Any

import httpx
import pytest
from serverproc import VASTRAY, ServerProcess, wait_for_job
from test_jobs import SLOW_SOURCE, wait_for_phase

from vastray.server.main import listening_socket


@pytest.mark.slow
def test_first_start_builds_the_demo_while_serving(tmp_path: Path) -> None:
    s = ServerProcess(tmp_path / "data", env={"VASTRAY_CACHE": "128M"}).start()
    try:
        with s.client() as api:
            # Usable at once: health, readiness and the API answer while the demo builds.
            ready = api.get("/readyz").json()
            assert ready["cache_budget_bytes"] == 128 << 20
            jobs = api.get("/api/jobs").json()
            assert [j["name"] for j in jobs] == ["demo"] and jobs[0]["source"] == "demo"
            models = api.get("/api/models").json()
            assert [(m["name"], m["state"]) for m in models] in ([("demo", "building")], [("demo", "ready")])
            done = wait_for_job(api, jobs[0]["id"])
            assert done["state"] == "succeeded"
            demo = api.get(f"/api/models/{done['model_id']}").json()
            assert demo["state"] == "ready" and demo["triangles"] > 100_000
        assert "building the demo model" in s.log() and "phase build" in s.log()
    finally:
        assert s.stop() == 0
    # A restart keeps it and does not build it again.
    s.start()
    try:
        with s.client() as api:
            assert [m["name"] for m in api.get("/api/models").json()] == ["demo"]
            assert len(api.get("/api/jobs").json()) == 1
    finally:
        s.stop()


def a_model_and_a_running_build(s: ServerProcess) -> tuple[dict[str, Any], dict[str, Any], list[int]]:
    """(a built model's job, a job caught mid-build, its worker processes)."""
    with s.client() as api:
        kept = api.post("/api/jobs", json={"source": "scene:spheres:2000:1", "name": "kept"}).json()
        wait_for_job(api, kept["id"])
        job = api.post("/api/jobs", json={"source": SLOW_SOURCE, "name": "caught"}).json()
        wait_for_phase(api, job["id"], ("read", "build"))
        workers = s.workers()
    assert workers
    return kept, job, workers


@pytest.mark.slow
@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_clean_shutdown_interrupts_running_jobs(tmp_path: Path, sig: int) -> None:
    s = ServerProcess(tmp_path / "data", "--no-demo").start()
    kept, job, workers = a_model_and_a_running_build(s)
    start = time.monotonic()
    assert s.stop(sig) == 0
    assert time.monotonic() - start < 15
    assert all(not Path(f"/proc/{pid}").exists() for pid in workers), "a build worker outlived the server"
    assert not any((s.data_dir / "jobs").iterdir()), "partial output left behind"
    s.start()
    try:
        with s.client() as api:
            after = api.get(f"/api/jobs/{job['id']}").json()
            assert after["state"] == "interrupted" and "shut down" in after["error"]
            assert api.get(f"/api/models/{job['model_id']}").status_code == 404
            assert api.get(f"/api/models/{kept['model_id']}").json()["state"] == "ready"
    finally:
        s.stop()


@pytest.mark.slow
def test_crash_restart_keeps_the_registry_and_marks_interrupted_jobs(tmp_path: Path) -> None:
    s = ServerProcess(tmp_path / "data", "--no-demo").start()
    kept, job, workers = a_model_and_a_running_build(s)
    s.stop(signal.SIGKILL)
    deadline = time.monotonic() + 10
    while any(Path(f"/proc/{pid}").exists() for pid in workers) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert not any(Path(f"/proc/{pid}").exists() for pid in workers), "the worker outlived a crashed server"
    s.start()
    try:
        with s.client() as api:
            after = api.get(f"/api/jobs/{job['id']}").json()
            assert after["state"] == "interrupted" and "interrupted" in after["error"]
            assert api.get(f"/api/models/{job['model_id']}").status_code == 404
            model = api.get(f"/api/models/{kept['model_id']}").json()
            assert model["state"] == "ready"
            assert (
                api.post(
                    f"/api/models/{model['id']}/render", json={"camera": {"width": 16, "height": 16}}
                ).status_code
                == 200
            )
        assert not any((s.data_dir / "jobs").iterdir())
        assert "interrupted" in s.log()
    finally:
        s.stop()
    # A model file removed behind the server's back is forgotten at the next start.
    (s.data_dir / model["file"]).unlink()
    s.start()
    try:
        with s.client() as api:
            assert api.get(f"/api/models/{model['id']}").status_code == 404
        assert "the file is missing" in s.log()
    finally:
        s.stop()


@pytest.mark.slow
def test_delete_while_rendering_is_deferred(tmp_path: Path) -> None:
    s = ServerProcess(tmp_path / "data", "--no-demo").start()
    try:
        with s.client() as api:
            job = api.post("/api/jobs", json={"source": "scene:plant:200000:4"}).json()
            model_id = wait_for_job(api, job["id"])["model_id"]
            file = s.data_dir / api.get(f"/api/models/{model_id}").json()["file"]
            result: dict[str, Any] = {}

            def slow_render() -> None:
                with s.client() as c:
                    result["r"] = c.post(
                        f"/api/models/{model_id}/render",
                        json={
                            "camera": {"width": 1920, "height": 1080},
                            "quality": {"shading": "sun"},
                        },
                    )

            t = threading.Thread(target=slow_render)
            t.start()
            deadline = time.monotonic() + 30
            while api.get(f"/api/models/{model_id}").json()["in_use"] == 0:
                assert time.monotonic() < deadline and t.is_alive(), "the render never started"
                time.sleep(0.01)
            r = api.delete(f"/api/models/{model_id}")
            assert r.status_code == 202 and r.json()["status"] == "deleting"
            assert api.get(f"/api/models/{model_id}").status_code == 404
            assert model_id not in {m["id"] for m in api.get("/api/models").json()}
            assert file.exists(), "deleted under a running render"
            t.join(120)
            assert result["r"].status_code == 200 and result["r"].headers["x-vastray-complete"] == "true"
            deadline = time.monotonic() + 10
            while file.exists() and time.monotonic() < deadline:
                time.sleep(0.05)
            assert not file.exists(), "the file stayed after its last user left"
            assert api.post(f"/api/models/{model_id}/render", json={}).status_code == 404
    finally:
        s.stop()


def test_a_viewer_leaving_a_deleted_model_mid_frame(tmp_path: Path) -> None:
    """A viewer's lease on a model lasts until no frame of its view renders any more. A
    model deleted while viewed goes when its last viewer leaves; if the viewer vanishes
    while a refining frame still traces the model, closing it then would free what the
    frame reads (the server died of it). Each round: a slow frame in flight, the model
    deleted, the socket aborted; the server lives on and each file goes once its frame
    is done."""
    from test_stream import Viewer, orbit, run

    s = ServerProcess(tmp_path / "data", "--no-demo").start()
    try:
        with s.client() as api:
            sources = [f"scene:plant:150000:{seed}" for seed in (1, 2, 3)]
            jobs = [api.post("/api/jobs", json={"source": source}).json() for source in sources]
            models = [wait_for_job(api, j["id"])["model_id"] for j in jobs]
            files = [s.data_dir / api.get(f"/api/models/{m}").json()["file"] for m in models]

            async def leave_mid_frame(model_id: str) -> None:
                v = Viewer(s, model_id, viewport={"width": 1920, "height": 1080})
                await v.__aenter__()
                await v.send({"type": "quality", "shading": "sun"})
                await v.camera(*orbit(v.welcome, 0.4))
                # The first frame of a moving camera is small; the refinement after it,
                # at full size with shadow rays, is what is in flight when the viewer goes.
                while not v.frames:
                    await v.recv()
                r = api.delete(f"/api/models/{model_id}")
                assert r.status_code == 202 and r.json()["status"] == "deleting"
                v.ws.transport.abort()

            for model_id in models:
                run(leave_mid_frame(model_id))
            deadline = time.monotonic() + 60
            while any(f.exists() for f in files) and time.monotonic() < deadline:
                assert s.proc.poll() is None, "the server died"
                time.sleep(0.05)
            assert s.proc.poll() is None, "the server died"
            assert not any(f.exists() for f in files), "a file stayed after its last viewer left"
            assert api.get("/healthz").status_code == 200
            assert all(api.get(f"/api/models/{m}").status_code == 404 for m in models)
        assert "Traceback" not in s.log()
    finally:
        s.stop()


def test_a_new_registry_says_so_and_an_old_one_says_what_it_migrates(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    from vastray.server.registry import MIGRATIONS, SCHEMA_VERSION, Registry

    caplog.set_level(logging.INFO, logger="vastray.registry")
    Registry(tmp_path).close()
    said = [r.getMessage() for r in caplog.records]
    assert any(m.startswith("registry: new at") for m in said), said
    assert not any("migrating" in m for m in said), said
    # A file as schema 1 made it, with a model in it: reopening names each step it runs,
    # and the model is still there, upright (+y) as models were before they had an up.
    caplog.clear()
    old = tmp_path / "old"
    old.mkdir()
    with sqlite3.connect(old / "registry.sqlite3") as db:
        db.executescript(MIGRATIONS[0] + "PRAGMA user_version = 1;")
        db.execute(
            "INSERT INTO models (id, name, state, file, created_at, info) "
            "VALUES ('mdl_old', 'old', 'ready', 'old.vast', 0, '{}')"
        )
    registry = Registry(old)
    said = [r.getMessage() for r in caplog.records if "registry:" in r.getMessage()]
    assert said == [f"registry: migrating schema {v} -> {v + 1}" for v in range(1, SCHEMA_VERSION)], said
    row = registry.model("mdl_old")
    registry.close()
    assert row is not None and row.name == "old" and row.up is None


def test_registry_from_a_newer_release_is_refused(tmp_path: Path) -> None:
    data = tmp_path / "data"
    s = ServerProcess(data, "--no-demo").start()
    s.stop()
    with sqlite3.connect(data / "registry.sqlite3") as db:
        db.execute("PRAGMA user_version = 99")
    out = subprocess.run(
        [str(VASTRAY), "serve", "--data", str(data), "--port", "0", "--no-demo"],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert out.returncode != 0
    assert "schema version 99 is newer" in out.stderr


def test_bad_settings_are_clear_errors(tmp_path: Path) -> None:
    for args, message in [
        (["--cache", "lots"], "not a size"),
        (["--api-key", "short"], "at least 16 characters"),
        (["--port", "70000"], "port"),
    ]:
        out = subprocess.run(
            [str(VASTRAY), "serve", "--data", str(tmp_path / "d"), *args],
            capture_output=True,
            text=True,
            timeout=60,
        )
        assert out.returncode == 2 and message in out.stderr, (args, out.stderr)
        assert "Traceback" not in out.stderr


def test_port_in_use_is_a_clear_error(server: ServerProcess) -> None:
    port = httpx.URL(server.url).port
    out = subprocess.run(
        [str(VASTRAY), "serve", "--data", str(server.data_dir.parent / "x"), "--port", str(port)],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert out.returncode == 2 and "cannot listen" in out.stderr


def test_connections_to_the_server_send_without_delay() -> None:
    """Connections accepted from the server's socket have TCP_NODELAY (inherited from
    the listening socket; uvloop does not set it): with Nagle's algorithm on, a frame's
    stats event waited for the client's delayed ACK, and a reader that waits for a
    frame and its stats briefly fell behind (test_stream's fast reader)."""
    server = listening_socket("127.0.0.1", 0)
    server.listen()
    with server, socket.create_connection(server.getsockname()) as client:
        accepted, _ = server.accept()
        with accepted:
            assert accepted.getsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY) != 0
    assert client.fileno() == -1  # closed by the with block


def test_a_port_in_use_is_refused() -> None:
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        with pytest.raises(OSError):
            listening_socket("127.0.0.1", taken.getsockname()[1])
