"""The server against the command line, side by side in one run: a build job against
`vastray build` of the same input, a one-shot render against `vastray render` of the
same view (full detail, cold cache: each a fresh process or a model just opened), and
the server's CPU and memory while idle.

    python bench/server.py [--source scene:plant:2000000:1] [--repeats 3]

Results go to bench/results/server.md.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import httpx

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import RESULTS_DIR, machine_info, markdown_table

from vastray.server.process import VASTRAY, ServerProcess

SIZE = (1280, 720)


def cpu_seconds(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def rss_mib(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return 0.0


def wait_job(api: httpx.Client, job_id: str) -> dict[str, Any]:
    while (job := api.get(f"/api/jobs/{job_id}").json())["state"] in ("queued", "running"):
        time.sleep(0.05)
    assert job["state"] == "succeeded", job
    return job


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--source", default="scene:plant:2000000:1")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--out", default=str(RESULTS_DIR / "server.md"))
    args = ap.parse_args()
    builds: dict[str, list[float]] = {"cli": [], "job": []}
    renders: dict[str, list[float]] = {"cli": [], "api": []}
    with tempfile.TemporaryDirectory(prefix="vastray-bench-") as tmp:
        tmp_path = Path(tmp)
        server = ServerProcess(tmp_path / "data", "--no-demo").start()
        try:
            api = httpx.Client(
                base_url=server.url, headers={"Authorization": f"Bearer {server.key}"}, timeout=900
            )
            idle_before = cpu_seconds(server.pid), time.monotonic()
            time.sleep(5)
            idle_cpu = 100 * (cpu_seconds(server.pid) - idle_before[0]) / (time.monotonic() - idle_before[1])
            idle_rss = rss_mib(server.pid)
            model_id = ""
            for k in range(args.repeats):  # interleaved, so both see the same machine
                out = tmp_path / f"cli-{k}.vast"
                start = time.perf_counter()
                subprocess.run(
                    [str(VASTRAY), "build", args.source, "-o", str(out)], check=True, capture_output=True
                )
                builds["cli"].append(time.perf_counter() - start)
                start = time.perf_counter()
                job = api.post("/api/jobs", json={"source": args.source, "name": f"bench-{k}"}).json()
                done = wait_job(api, job["id"])
                builds["job"].append(time.perf_counter() - start)
                model_id = done["model_id"]
                triangles = done["report"]["triangles"]
            info = api.get(f"/api/models/{model_id}").json()
            cli_model = tmp_path / "cli-0.vast"
            camera = {"width": SIZE[0], "height": SIZE[1]}
            for k in range(args.repeats):
                start = time.perf_counter()
                subprocess.run(
                    [
                        str(VASTRAY),
                        "render",
                        str(cli_model),
                        "--size",
                        f"{SIZE[0]}x{SIZE[1]}",
                        "--shading",
                        "sun",
                        "-o",
                        str(tmp_path / "cli.png"),
                    ],
                    check=True,
                    capture_output=True,
                )
                renders["cli"].append(time.perf_counter() - start)
                # A fresh model for the server too: a copy registered in place (cold in the cache).
                copy = server.data_dir / f"copy-{k}.vast"
                copy.write_bytes(cli_model.read_bytes())
                fresh = api.post("/api/models", json={"path": copy.name}).json()["model"]["id"]
                start = time.perf_counter()
                r = api.post(
                    f"/api/models/{fresh}/render", json={"camera": camera, "quality": {"shading": "sun"}}
                )
                renders["api"].append(time.perf_counter() - start)
                assert r.status_code == 200 and r.headers["x-vastray-complete"] == "true"
            busy_rss = rss_mib(server.pid)
        finally:
            server.stop()
    runs = {**{f"build_{k}": v for k, v in builds.items()}, **{f"render_{k}": v for k, v in renders.items()}}
    med = {k: statistics.median(v) for k, v in runs.items()}
    rows = [
        [
            "build job vs `vastray build`",
            f"{med['build_job']:.2f} s",
            f"{med['build_cli']:.2f} s",
            f"{med['build_cli'] / med['build_job']:.2f}x",
            f"{triangles / med['build_job'] / 1e6:.2f} vs {triangles / med['build_cli'] / 1e6:.2f} Mtri/s",
        ],
        [
            f"one-shot render vs `vastray render` ({SIZE[0]}x{SIZE[1]} sun, full detail, cold)",
            f"{med['render_api']:.2f} s",
            f"{med['render_cli']:.2f} s",
            f"{med['render_cli'] / med['render_api']:.2f}x",
            "CLI: process start, open, render, write; API: request, open, render, PNG",
        ],
    ]
    text = "\n".join(
        [
            "# The server against the command line",
            "",
            f"`python bench/server.py --source {args.source}` ({info['triangles']:,} triangles); medians of "
            f"{args.repeats} interleaved runs. Ratios > 1: the server is faster.",
            "",
            *(f"- {k}: {v}" for k, v in machine_info().items()),
            "",
            markdown_table(["measure", "server", "CLI", "CLI / server", "note"], rows),
            "",
            f"Idle server (no models open): {idle_cpu:.2f} % of one core over 5 s, "
            f"{idle_rss:.0f} MiB resident; "
            f"{busy_rss:.0f} MiB after the runs above (cache budget 1 GiB).",
            "",
            "Raw times (s): " + json.dumps({k: [round(x, 3) for x in v] for k, v in runs.items()}),
        ]
    )
    Path(args.out).write_text(text + "\n")
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
