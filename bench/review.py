"""Design-review benchmark: a review with 1, 4 and 8 followers against as many
independent viewers moving along the same camera path — frames/s per client, server
CPU, frames rendered and bytes sent — and pick latency (p50/p95) while the display
streams.

    python bench/review.py [--followers 1,4,8] [--seconds 8] [--model demo]

A real server in its own process; the clients in this one parse frame headers but do
not decode images. Results go to bench/results/review.md.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import math
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import websockets

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import RESULTS_DIR, machine_info, markdown_table
from stream import cpu_seconds, model_source

from vastray.protocol import FrameHeader
from vastray.server.process import ServerProcess

WIDTH, HEIGHT = 960, 540
CAMERA_HZ = 60.0
PICK_EVERY = 0.25  # seconds between the presenter's picks while it moves


def metric(server: ServerProcess, name: str) -> float:
    text = httpx.get(f"{server.url}/metrics").text
    line = next((x for x in text.splitlines() if x.startswith(name)), None)
    return float(line.split()[-1]) if line else 0.0


class Client:
    def __init__(
        self, server: ServerProcess, model: str, token: str, review: str | None, drives: bool
    ) -> None:
        self.url = server.url.replace("http://", "ws://") + "/api/stream"
        self.hello = {
            "type": "hello",
            "protocol": 1,
            "model": model,
            "token": token,
            "review": review,
            "viewport": {"width": WIDTH, "height": HEIGHT},
        }
        self.drives = drives
        self.frames = 0
        self.bytes = 0
        self.picks: list[float] = []

    async def run(self, seconds: float, bounds: Any, phase: float, pick: bool) -> None:
        lo, hi = (np.asarray(b) for b in bounds)
        centre, size = (lo + hi) / 2, float(np.linalg.norm(hi - lo))
        async with websockets.connect(self.url, max_size=1 << 26) as ws:
            await ws.send(json.dumps(self.hello))
            while json.loads(await ws.recv())["type"] != "welcome":
                pass
            start = time.monotonic()
            asked: dict[str, float] = {}

            async def drive() -> None:
                seq, last_pick = 0, 0.0
                while (t := time.monotonic() - start) < seconds:
                    seq += 1
                    a = 0.6 * t + phase
                    eye = (centre + size * 0.8 * np.array([math.cos(a), 0.45, math.sin(a)])).tolist()
                    await ws.send(
                        json.dumps({"type": "camera", "seq": seq, "eye": eye, "target": centre.tolist()})
                    )
                    if pick and t - last_pick > PICK_EVERY:
                        last_pick = t
                        pid = f"p{seq}"
                        asked[pid] = time.perf_counter()
                        await ws.send(
                            json.dumps({"type": "pick", "id": pid, "points": [[WIDTH / 2, HEIGHT / 2]]})
                        )
                    await asyncio.sleep(1 / CAMERA_HZ)

            driver = asyncio.create_task(drive()) if self.drives else None
            try:
                while time.monotonic() - start < seconds:
                    try:
                        m = await asyncio.wait_for(ws.recv(), 0.5)
                    except TimeoutError:
                        continue
                    if isinstance(m, bytes):
                        h = FrameHeader.unpack(m)
                        self.frames += 1
                        self.bytes += len(m)
                        await ws.send(json.dumps({"type": "ack", "frame": h.frame}))
                    else:
                        event = json.loads(m)
                        if event["type"] == "pick_result" and event["id"] in asked:
                            self.picks.append(1000 * (time.perf_counter() - asked.pop(event["id"])))
            finally:
                if driver is not None:
                    driver.cancel()


async def run_case(
    server: ServerProcess, model: dict[str, Any], n: int, seconds: float, review: bool
) -> dict[str, Any]:
    with httpx.Client(base_url=server.url, headers={"Authorization": f"Bearer {server.key}"}) as api:
        if review:
            r = api.post("/api/reviews", json={"model": model["id"]}).json()
            presenter = Client(server, model["id"], r["presenter_token"], r["review"]["id"], drives=True)
            clients = [presenter] + [
                Client(server, model["id"], r["join_token"], r["review"]["id"], drives=False)
                for _ in range(n)
            ]
        else:
            clients = [Client(server, model["id"], server.key or "", None, drives=True) for _ in range(n + 1)]
    rendered0, sent0 = (
        metric(server, 'vastray_frames_total{kind="stream"}'),
        metric(server, 'vastray_frames_sent_total{kind="stream"}'),
    )
    cpu0, t0 = cpu_seconds(server.pid), time.monotonic()
    # The same camera path for every driver: independent viewers do the work a review shares.
    await asyncio.gather(
        *(c.run(seconds, model["bounds"], 0.0, pick=(i == 0)) for i, c in enumerate(clients))
    )
    cpu = (cpu_seconds(server.pid) - cpu0) / (time.monotonic() - t0)
    rendered = metric(server, 'vastray_frames_total{kind="stream"}') - rendered0
    sent = metric(server, 'vastray_frames_sent_total{kind="stream"}') - sent0
    picks = clients[0].picks
    return {
        "kind": "review" if review else "independent",
        "followers": n,
        "clients": len(clients),
        "fps_per_client": statistics.mean(c.frames / seconds for c in clients),
        "fps_min": min(c.frames / seconds for c in clients),
        "server_cpu_cores": cpu,
        "frames_rendered_per_s": rendered / seconds,
        "frames_sent_per_s": sent / seconds,
        "mbit_total": sum(8 * c.bytes for c in clients) / seconds / 1e6,
        "pick_p50_ms": float(np.percentile(picks, 50)) if picks else math.nan,
        "pick_p95_ms": float(np.percentile(picks, 95)) if picks else math.nan,
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--followers", default="1,4,8")
    ap.add_argument("--seconds", type=float, default=8.0)
    ap.add_argument("--model", default="demo")
    ap.add_argument("--out", default=str(RESULTS_DIR / "review.md"))
    args = ap.parse_args()
    rows = []
    with tempfile.TemporaryDirectory(prefix="vastray-bench-") as tmp:
        server = ServerProcess(Path(tmp) / "data", "--no-demo").start()
        try:
            with httpx.Client(
                base_url=server.url, headers={"Authorization": f"Bearer {server.key}"}, timeout=600
            ) as api:
                job = api.post("/api/jobs", json={"source": model_source(args.model)}).json()
                while (info := api.get(f"/api/jobs/{job['id']}").json())["state"] in ("queued", "running"):
                    time.sleep(0.5)
                model = api.get(f"/api/models/{info['model_id']}").json()
            for n in (int(x) for x in args.followers.split(",")):
                for review in (True, False):
                    row = asyncio.run(run_case(server, model, n, args.seconds, review))
                    rows.append(row)
                    print(
                        f"  {row['kind']} +{n}: {row['fps_per_client']:.1f} fps/client, "
                        f"CPU {row['server_cpu_cores']:.2f} cores, "
                        f"rendered {row['frames_rendered_per_s']:.1f}/s, "
                        f"sent {row['frames_sent_per_s']:.1f}/s, "
                        f"pick p95 {row['pick_p95_ms']:.0f} ms",
                        file=sys.stderr,
                        flush=True,
                    )
        finally:
            server.stop()
    headers = [
        "",
        "followers",
        "clients",
        "fps/client (min)",
        "server CPU (cores)",
        "frames rendered/s",
        "frames sent/s",
        "Mbit/s total",
        "pick p50 ms",
        "pick p95 ms",
    ]
    table = [
        [
            r["kind"],
            r["followers"],
            r["clients"],
            f"{r['fps_per_client']:.1f} ({r['fps_min']:.1f})",
            f"{r['server_cpu_cores']:.2f}",
            f"{r['frames_rendered_per_s']:.1f}",
            f"{r['frames_sent_per_s']:.1f}",
            f"{r['mbit_total']:.1f}",
            f"{r['pick_p50_ms']:.0f}",
            f"{r['pick_p95_ms']:.0f}",
        ]
        for r in rows
    ]
    lines = [
        "# Design reviews: one render for every follower",
        "",
        f"`python bench/review.py` — model `{args.model}` ({model['triangles']:,} triangles), "
        f"{WIDTH}x{HEIGHT}, {args.seconds:g} s of camera path at {CAMERA_HZ:g} Hz. "
        "A review: the presenter moves, followers follow. "
        "Independent: as many viewers, each moving along the same path. Picks: the presenter (or the first "
        f"viewer) picks the image centre every {PICK_EVERY:g} s while it moves.",
        "",
        *(f"- {k}: {v}" for k, v in machine_info().items()),
        "",
        markdown_table(headers, table),
    ]
    Path(args.out).write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
