"""Build jobs that do not end well: cancelled, killed mid-build, a mesh that does not
parse, a budget the server does not allow. Each fails alone, with its reason; the
server keeps serving and nothing of the job stays in the data directory."""

from __future__ import annotations

import os
import signal
import time
from pathlib import Path

import httpx
import pytest
from serverproc import ServerProcess, wait_for_job

# Big enough to be caught mid-build on a fast machine (a few seconds on 2 cores).
SLOW_SOURCE = "scene:plant:3000000:5"


def wait_for_phase(api: httpx.Client, job_id: str, phases: tuple[str, ...], timeout: float = 120.0) -> dict:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        job = api.get(f"/api/jobs/{job_id}").json()
        if job["state"] == "running" and job["phase"] in phases:
            return job
        assert job["state"] in ("queued", "running"), job
        time.sleep(0.05)
    raise AssertionError(f"job {job_id} never reached {phases}")


def nothing_left(server: ServerProcess, job_id: str) -> None:
    assert not (server.data_dir / "jobs" / job_id).exists()
    partial = [p for p in (server.data_dir / "models").iterdir() if p.name.startswith(".")]
    assert not partial, partial


def still_serving(api: httpx.Client) -> None:
    r = api.post("/api/jobs", json={"source": "scene:spheres:3000:1", "name": "after"})
    assert r.status_code == 202, r.text
    assert wait_for_job(api, r.json()["id"])["state"] == "succeeded"


@pytest.mark.slow
def test_cancel_a_running_build(server: ServerProcess, api: httpx.Client) -> None:
    r = api.post("/api/jobs", json={"source": SLOW_SOURCE, "name": "to cancel"})
    assert r.status_code == 202
    job = r.json()
    model_id = job["model_id"]
    assert api.get(f"/api/models/{model_id}").json()["state"] == "building"
    wait_for_phase(api, job["id"], ("read", "build"))
    r = api.post(f"/api/jobs/{job['id']}/cancel")
    assert r.status_code == 200
    done = wait_for_job(api, job["id"])
    assert done["state"] == "cancelled" and "cancelled" in done["error"]
    assert api.get(f"/api/models/{model_id}").status_code == 404  # its reserved model is gone
    nothing_left(server, job["id"])
    assert api.post(f"/api/jobs/{job['id']}/cancel").json()["state"] == "cancelled"  # idempotent
    still_serving(api)


def test_cancel_a_queued_build(server: ServerProcess, api: httpx.Client) -> None:
    first = api.post("/api/jobs", json={"source": SLOW_SOURCE}).json()
    second = api.post("/api/jobs", json={"source": "scene:spheres:2000:3"}).json()
    assert api.get(f"/api/jobs/{second['id']}").json()["state"] == "queued"  # one job at a time
    cancelled = api.post(f"/api/jobs/{second['id']}/cancel").json()
    assert cancelled["state"] == "cancelled" and "before it started" in cancelled["error"]
    api.post(f"/api/jobs/{first['id']}/cancel")
    assert wait_for_job(api, first["id"])["state"] == "cancelled"
    assert wait_for_job(api, second["id"])["state"] == "cancelled"


@pytest.mark.slow
def test_worker_killed_mid_build(server: ServerProcess, api: httpx.Client) -> None:
    """SIGKILL of the worker (as the kernel's OOM killer does): the job fails saying so,
    the server lives on, and nothing of the job stays."""
    job = api.post("/api/jobs", json={"source": SLOW_SOURCE, "name": "to kill"}).json()
    wait_for_phase(api, job["id"], ("read", "build"))
    workers = server.workers()
    assert len(workers) == 1, workers
    os.kill(workers[0], signal.SIGKILL)
    done = wait_for_job(api, job["id"])
    assert done["state"] == "failed" and "SIGKILL" in done["error"] and "memory" in done["error"]
    nothing_left(server, job["id"])
    assert api.get(f"/api/models/{job['model_id']}").status_code == 404
    still_serving(api)


@pytest.mark.slow
def test_memory_watchdog(tmp_path: Path) -> None:
    """A worker whose resident memory passes (budget + fixed overhead) x slack is stopped
    by the server, and the job says why. The builder keeps within its budget, so the test
    sets a slack below what any Python process needs to start."""
    s = ServerProcess(tmp_path / "data", "--no-demo", env={"VASTRAY_BUILD_RSS_SLACK": "0.2"}).start()
    try:
        with s.client() as api:
            job = api.post("/api/jobs", json={"source": SLOW_SOURCE, "options": {"memory": "32M"}}).json()
            done = wait_for_job(api, job["id"])
            assert done["state"] == "failed", done
            assert "exceeded the job's limit" in done["error"] and "32 MiB" in done["error"]
            assert not (s.data_dir / "jobs" / job["id"]).exists()
            r = api.post("/api/jobs", json={"source": "demo", "options": {"memory": "1M"}})
            assert r.status_code == 422 and "memory budget too small" in r.json()["error"]["message"]
    finally:
        s.stop()


def test_a_mesh_that_does_not_parse_fails_its_job(server: ServerProcess, api: httpx.Client) -> None:
    r = api.post(
        "/api/uploads",
        params={"filename": "broken.ply", "register": "true"},
        content=b"ply\nformat binary_little_endian 1.0\nelement vertex 3\nend_header\n\x00\x01",
    )
    assert r.status_code == 201, r.text
    job = r.json()["created"]["job"]
    done = wait_for_job(api, job["id"])
    assert done["state"] == "failed"
    assert "broken.ply" in done["error"], done["error"]
    nothing_left(server, job["id"])
    still_serving(api)


def test_bad_sources_and_options(api: httpx.Client) -> None:
    cases = [
        ({"source": "scene:nosuch:100:1"}, 422, "unknown scene"),
        ({"source": "scene:plant:lots:1"}, 422, "must be numbers"),
        ({"source": "missing.ply"}, 404, "no such file"),
        ({"source": "../etc/passwd"}, 403, "outside the data directory"),
        ({"source": "/etc/passwd"}, 403, "relative to the data directory"),
        ({"source": "demo", "options": {"memory": "lots"}}, 422, "memory budget"),
        ({"source": "demo", "options": {"memory": "64G"}}, 422, "over this server's limit"),
        ({"source": "demo", "options": {"threads": -1}}, 422, "threads"),
        ({"source": "demo", "upload": "upl-000000000000"}, 422, "exactly one"),
        ({"upload": "upl-000000000000"}, 404, "no upload"),
        ({"source": "demo", "colour": "red"}, 422, "colour"),
    ]
    for body, status, message in cases:
        r = api.post("/api/jobs", json=body)
        assert r.status_code == status, (body, r.text)
        assert message in r.json()["error"]["message"], (body, r.json())
    assert api.get("/api/jobs/job-nosuch").status_code == 404


@pytest.mark.parametrize("source", ["demo"])
def test_jobs_list_and_filter(api: httpx.Client, source: str) -> None:
    job = api.post("/api/jobs", json={"source": "scene:spheres:1000:9", "name": "listed"}).json()
    wait_for_job(api, job["id"])
    listed = api.get("/api/jobs", params={"state": "succeeded"}).json()
    assert job["id"] in {j["id"] for j in listed}
    assert all(j["state"] == "succeeded" for j in listed)


def test_a_build_with_quantized_splits(server: ServerProcess, api: httpx.Client) -> None:
    """The options (quantized splits and vertices) reach the builder: the job and the model
    record them, the file's header carries the flags, and the model renders."""
    from vastray.modelfile import FLAG_QUANTIZED_SPLITS, FLAG_QUANTIZED_VERTICES, ModelFile

    both = FLAG_QUANTIZED_SPLITS | FLAG_QUANTIZED_VERTICES
    options = {"quantized_splits": True, "quantized_vertices": True}
    body = {"source": "scene:spheres:2000:3", "options": options}
    job = api.post("/api/jobs", json=body)
    assert job.status_code == 202, job.text
    done = wait_for_job(api, job.json()["id"])
    assert done["state"] == "succeeded", done
    assert done["options"]["quantized_splits"] is True and done["options"]["quantized_vertices"] is True
    info = api.get(f"/api/models/{done['model_id']}").json()
    assert info["build"]["options"]["quantized_splits"] is True
    assert info["build"]["options"]["quantized_vertices"] is True
    flagged = []
    for path in (server.data_dir / "models").glob("*.vast"):
        with ModelFile(path) as model:
            flagged.append(model.header["flags"] & both == both)
    assert any(flagged)
    r = api.post(f"/api/models/{done['model_id']}/render", json={"camera": {"width": 32, "height": 24}})
    assert r.status_code == 200, r.text


def test_a_build_chooses_its_tier_width(server: ServerProcess, api: httpx.Client) -> None:
    """`tier_width` reaches the builder: 0 writes an untiered file, 2 a tiered one with
    fewer tiers than the default's; the job and the model record the width asked for, and
    a width outside 0 ... 16 is refused with the field named."""
    from vastray.modelfile import ModelFile

    files = {}
    for width in (0, 2):
        body = {"source": "scene:plant:20000:4", "name": f"tiers-{width}", "options": {"tier_width": width}}
        job = api.post("/api/jobs", json=body)
        assert job.status_code == 202, job.text
        done = wait_for_job(api, job.json()["id"])
        assert done["state"] == "succeeded", done
        assert done["options"]["tier_width"] == width
        info = api.get(f"/api/models/{done['model_id']}").json()
        assert info["build"]["options"]["tier_width"] == width
        files[width] = server.data_dir / "models" / f"{done['model_id']}.vast"
    default = api.post("/api/jobs", json={"source": "scene:plant:20000:4", "name": "tiers-default"}).json()
    done = wait_for_job(api, default["id"])
    assert "tier_width" not in done["options"]
    files[None] = server.data_dir / "models" / f"{done['model_id']}.vast"
    tiers = {}
    for width, path in files.items():
        with ModelFile(path) as model:
            tiers[width] = model.tier_count if model.tiered else 0
    assert tiers[0] == 0 and 0 < tiers[2] < tiers[None], tiers
    for bad in (-1, 17, "wide"):
        r = api.post("/api/jobs", json={"source": "scene:plant:2000:4", "options": {"tier_width": bad}})
        assert r.status_code == 422 and "tier_width" in r.text, r.text


def test_a_build_chooses_its_traversal_cost(server: ServerProcess, api: httpx.Client) -> None:
    """`traversal_cost` reaches the kd builder: 8 builds fewer leaves than the default 4
    from the same input, the job records it, and a cost that is not positive is refused."""
    from vastray.modelfile import ModelFile

    leaves = {}
    for cost in (None, 8):
        options = {} if cost is None else {"traversal_cost": cost}
        body = {"source": "scene:plant:20000:5", "name": f"cost-{cost}", "options": options}
        done = wait_for_job(api, api.post("/api/jobs", json=body).json()["id"])
        assert done["state"] == "succeeded", done
        assert done["options"].get("traversal_cost") == cost
        with ModelFile(server.data_dir / "models" / f"{done['model_id']}.vast") as model:
            leaves[cost] = model.header["leaves"]
    assert leaves[8] < leaves[None], leaves
    for bad in (0, -2, 100):
        r = api.post("/api/jobs", json={"source": "scene:plant:2000:4", "options": {"traversal_cost": bad}})
        assert r.status_code == 422 and "traversal_cost" in r.text, r.text


def test_a_build_names_a_layout_and_options_override_it(server: ServerProcess, api: httpx.Client) -> None:
    """`layout` sets the options vastray/layouts.py names for it, the job and the model
    record them, an option sent beside it wins, and the schema offers exactly those
    layouts: an unknown one is refused with a 422 naming the field."""
    from vastray.layouts import LAYOUTS
    from vastray.modelfile import ModelFile
    from vastray.schemas import BuildOptionsIn

    assert set(BuildOptionsIn.model_json_schema()["properties"]["layout"]["enum"]) == set(LAYOUTS)
    smallest = {"compact_triangles": True, "quantized_vertices": True, "tier_width": 0, "traversal_cost": 6}
    on = {"voxel_errors": True}  # every layout's default (with quantized splits)
    cases = [
        ({"layout": "smallest"}, {**smallest, **on, "lz4_hc_level": 9}),
        (
            {"layout": "smallest", "traversal_cost": 4, "lz4_hc_level": 0},
            {**smallest, **on, "traversal_cost": 4},
        ),
        ({"layout": "smaller"}, {"compact_triangles": True, **on}),
        ({"layout": "smaller", "voxel_errors": False}, {"compact_triangles": True}),
    ]
    for options, expected in cases:
        body = {"source": "scene:plant:20000:5", "options": options}
        done = wait_for_job(api, api.post("/api/jobs", json=body).json()["id"])
        assert done["state"] == "succeeded", done
        recorded = {k: v for k, v in done["options"].items() if k not in ("memory", "threads")}
        assert recorded == {"quantized_splits": True, **expected}, recorded
        assert api.get(f"/api/models/{done['model_id']}").json()["build"]["options"] == done["options"]
        with ModelFile(server.data_dir / "models" / f"{done['model_id']}.vast") as model:
            assert model.compact_triangles and model.tiered == ("tier_width" not in expected)
            assert model.quantized_vertices == expected.get("quantized_vertices", False)
            assert model.voxel_errors == expected.get("voxel_errors", False)
    r = api.post("/api/jobs", json={"source": "scene:plant:2000:4", "options": {"layout": "tiny"}})
    assert r.status_code == 422 and "layout" in r.text and "smallest" in r.text, r.text


def test_a_build_chooses_its_lz4_hc_level(server: ServerProcess, api: httpx.Client) -> None:
    """`lz4_hc_level` reaches the block compressor: the same input makes a smaller file of
    the same blocks, the job records the level, and a level past 12 is refused."""
    from vastray.modelfile import ModelFile

    sizes = {}
    for level in (None, 9):
        options = {} if level is None else {"lz4_hc_level": level}
        body = {"source": "scene:plant:20000:5", "name": f"hc-{level}", "options": options}
        done = wait_for_job(api, api.post("/api/jobs", json=body).json()["id"])
        assert done["state"] == "succeeded", done
        assert done["options"].get("lz4_hc_level") == level
        with ModelFile(server.data_dir / "models" / f"{done['model_id']}.vast") as model:
            sizes[level] = (model.header["file_size"], model.header["raw_bytes"])
    assert sizes[9][0] < sizes[None][0] and sizes[9][1] == sizes[None][1], sizes
    for bad in (-1, 13, "max"):
        r = api.post("/api/jobs", json={"source": "scene:plant:2000:4", "options": {"lz4_hc_level": bad}})
        assert r.status_code == 422 and "lz4_hc_level" in r.text, r.text
