"""Streaming benchmark: input-to-frame latency, frames/s and Mbit/s per viewer for 1, 2,
4 and 8 viewers at 1280x720 while their cameras move along a path, on the demo and on
a 10^7-triangle model; the share of frame time spent encoding; server memory with 8
viewers; CPU of an idle server whose views are finished.

    python bench/stream.py [--models demo,1e7] [--viewers 1,2,4,8] [--seconds 8]

A real `vastray serve` in its own process, real WebSocket clients in this one (they
parse frame headers but do not decode the images, so the clients' CPU stays out of the
server's way on a small machine). Latency is measured on the client: from sending a
camera message to receiving the first frame that shows it. Results go to
bench/results/stream.md (+ .csv, .png).
"""

from __future__ import annotations

import argparse
import asyncio
import csv
import json
import math
import os
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
from common import RESULTS_DIR, machine_info, markdown_table, pyplot, save_figure

from vastray.protocol import FrameHeader
from vastray.server.process import ServerProcess

CAMERA_HZ = 60.0  # how often a dragging user's camera changes
WIDTH, HEIGHT = 1280, 720
TARGET_P95_MS = 100.0
TARGET_FPS = 16.0


def model_source(name: str) -> str:
    if name == "demo":
        return "demo"
    return f"scene:plant:{int(float(name))}:1"


def percentile(values: list[float], q: float) -> float:
    return float(np.percentile(values, q)) if values else math.nan


class BenchViewer:
    def __init__(self, url: str, key: str, model: str, index: int, bounds: Any) -> None:
        self.url = url.replace("http://", "ws://") + "/api/stream"
        self.key = key
        self.model = model
        self.index = index
        lo, hi = (np.asarray(b) for b in bounds)
        self.centre = (lo + hi) / 2
        self.size = float(np.linalg.norm(hi - lo))
        self.sent: dict[int, float] = {}
        self.latencies: list[float] = []
        self.frames: list[dict[str, Any]] = []
        self.bytes = 0
        self.seq = 0
        self.answered = -1

    def eye(self, t: float) -> list[float]:
        # Orbit while flying in and out: every viewer on its own phase of the same path.
        a = 0.6 * t + 2 * math.pi * self.index / 8
        d = self.size * (0.75 + 0.35 * math.sin(0.4 * t))
        return (self.centre + d * np.array([math.cos(a), 0.45, math.sin(a)])).tolist()

    async def run(self, seconds: float, stop_moving: asyncio.Event | None = None) -> None:
        async with websockets.connect(self.url, max_size=1 << 26) as ws:
            await ws.send(
                json.dumps(
                    {
                        "type": "hello",
                        "protocol": 1,
                        "model": self.model,
                        "token": self.key,
                        "viewport": {"width": WIDTH, "height": HEIGHT},
                    }
                )
            )
            while json.loads(await ws.recv())["type"] != "welcome":
                pass
            start = time.monotonic()

            async def move() -> None:
                while time.monotonic() - start < seconds:
                    self.seq += 1
                    self.sent[self.seq] = time.perf_counter()
                    eye = self.eye(time.monotonic() - start)
                    await ws.send(
                        json.dumps(
                            {"type": "camera", "seq": self.seq, "eye": eye, "target": self.centre.tolist()}
                        )
                    )
                    await asyncio.sleep(1 / CAMERA_HZ)

            mover = asyncio.create_task(move())
            try:
                while time.monotonic() - start < seconds + 0.5:
                    try:
                        m = await asyncio.wait_for(ws.recv(), 1.0)
                    except TimeoutError:
                        continue
                    if isinstance(m, bytes):
                        h = FrameHeader.unpack(m)
                        now = time.perf_counter()
                        await ws.send(json.dumps({"type": "ack", "frame": h.frame}))
                        if time.monotonic() - start > seconds:
                            continue
                        self.bytes += len(m)
                        if h.camera_seq > self.answered and h.camera_seq in self.sent:
                            self.latencies.append(1000 * (now - self.sent[h.camera_seq]))
                            self.answered = h.camera_seq
                        self.frames.append(
                            {
                                "w": h.width,
                                "h": h.height,
                                "render": h.render_ms,
                                "encode": h.encode_ms,
                                "t": now,
                            }
                        )
            finally:
                mover.cancel()


async def run_viewers(
    server: ServerProcess, model: str, bounds: Any, n: int, seconds: float
) -> dict[str, Any]:
    viewers = [BenchViewer(server.url, server.key or "", model, i, bounds) for i in range(n)]
    rss_samples: list[int] = []

    async def sample_rss() -> None:
        while True:
            rss_samples.append(rss_bytes(server.pid))
            await asyncio.sleep(0.25)

    sampler = asyncio.create_task(sample_rss())
    await asyncio.gather(*(v.run(seconds) for v in viewers))
    sampler.cancel()
    latencies = [x for v in viewers for x in v.latencies]
    frames = [f for v in viewers for f in v.frames]
    fps = [len(v.frames) / seconds for v in viewers]
    mbit = [8 * v.bytes / seconds / 1e6 for v in viewers]
    pixels = sum(f["w"] * f["h"] for f in frames) / seconds
    busy = sum(f["render"] + f["encode"] for f in frames)
    return {
        "viewers": n,
        "p50_ms": percentile(latencies, 50),
        "p95_ms": percentile(latencies, 95),
        "fps_per_viewer": statistics.mean(fps),
        "fps_min": min(fps),
        "mbit_per_viewer": statistics.mean(mbit),
        "mpixels_per_s": pixels / 1e6,
        "mean_scale": statistics.mean(math.sqrt(f["w"] * f["h"] / (WIDTH * HEIGHT)) for f in frames)
        if frames
        else 0,
        "encode_share": sum(f["encode"] for f in frames) / busy if busy else math.nan,
        "render_ms": statistics.mean(f["render"] for f in frames) if frames else math.nan,
        "peak_rss_mib": max(rss_samples) / 2**20 if rss_samples else math.nan,
    }


def rss_bytes(pid: int) -> int:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) * 1024
    return 0


def cpu_seconds(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


async def idle_cpu(server: ServerProcess, model: str, viewers: int, seconds: float) -> dict[str, float]:
    """CPU of the server while `viewers` connected views sit finished."""
    url = server.url.replace("http://", "ws://") + "/api/stream"
    sockets = []
    for _ in range(viewers):
        ws = await websockets.connect(url, max_size=1 << 26)
        await ws.send(
            json.dumps(
                {
                    "type": "hello",
                    "protocol": 1,
                    "model": model,
                    "token": server.key,
                    "viewport": {"width": WIDTH, "height": HEIGHT},
                }
            )
        )
        sockets.append(ws)

    async def until_final(ws: Any) -> None:
        while True:
            m = await ws.recv()
            if isinstance(m, bytes):
                h = FrameHeader.unpack(m)
                await ws.send(json.dumps({"type": "ack", "frame": h.frame}))
                if h.final:
                    return

    await asyncio.gather(*(until_final(ws) for ws in sockets))
    await asyncio.sleep(0.5)
    c0, t0 = cpu_seconds(server.pid), time.monotonic()
    await asyncio.sleep(seconds)
    c1, t1 = cpu_seconds(server.pid), time.monotonic()
    for ws in sockets:
        await ws.close()
    return {"idle_cpu_percent": 100 * (c1 - c0) / (t1 - t0), "idle_rss_mib": rss_bytes(server.pid) / 2**20}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--models", default="demo,1e7", help="'demo' and/or triangle counts of the plant scene")
    ap.add_argument("--viewers", default="1,2,4,8")
    ap.add_argument("--seconds", type=float, default=8.0, help="camera path length per run")
    ap.add_argument("--cache", default="2G")
    ap.add_argument("--out", default=str(RESULTS_DIR / "stream"))
    args = ap.parse_args()
    counts = [int(x) for x in args.viewers.split(",")]
    rows: list[dict[str, Any]] = []
    extra: dict[str, Any] = {}
    with tempfile.TemporaryDirectory(prefix="vastray-bench-") as tmp:
        server = ServerProcess(Path(tmp) / "data", "--no-demo", "--cache", args.cache).start()
        try:
            api = httpx.Client(
                base_url=server.url, headers={"Authorization": f"Bearer {server.key}"}, timeout=600
            )
            for name in args.models.split(","):
                print(f"building {name} ...", file=sys.stderr, flush=True)
                job = api.post("/api/jobs", json={"source": model_source(name), "name": name}).json()
                while (info := api.get(f"/api/jobs/{job['id']}").json())["state"] in ("queued", "running"):
                    time.sleep(0.5)
                assert info["state"] == "succeeded", info
                model = api.get(f"/api/models/{job['model_id']}").json()
                for n in counts:
                    row = asyncio.run(run_viewers(server, model["id"], model["bounds"], n, args.seconds))
                    row.update(model=name, triangles=model["triangles"])
                    rows.append(row)
                    print(
                        f"  {name} x{n}: p50 {row['p50_ms']:.0f} ms, p95 {row['p95_ms']:.0f} ms, "
                        f"{row['fps_per_viewer']:.1f} fps/viewer, "
                        f"{row['mbit_per_viewer']:.1f} Mbit/s/viewer, "
                        f"scale {row['mean_scale']:.2f}",
                        file=sys.stderr,
                        flush=True,
                    )
                idle = asyncio.run(idle_cpu(server, model["id"], max(counts), 5.0))
                extra[name] = idle
                print(
                    f"  {name} idle with {max(counts)} finished views: {idle['idle_cpu_percent']:.2f} % CPU",
                    file=sys.stderr,
                )
        finally:
            server.stop()
    write(rows, extra, Path(args.out), args)
    return 0


def write(rows: list[dict[str, Any]], idle: dict[str, Any], out: Path, args: argparse.Namespace) -> None:
    out.parent.mkdir(parents=True, exist_ok=True)
    with open(out.with_suffix(".csv"), "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    headers = [
        "model",
        "viewers",
        "p50 ms",
        "p95 ms",
        "fps/viewer (min)",
        "Mbit/s/viewer",
        "Mpixel/s total",
        "vs 1 viewer",
        "mean scale",
        "encode share",
        "peak RSS MiB",
    ]
    table = []
    for r in rows:
        single = next(
            x for x in rows if x["model"] == r["model"] and x["viewers"] == min(v["viewers"] for v in rows)
        )
        table.append(
            [
                r["model"],
                r["viewers"],
                f"{r['p50_ms']:.0f}",
                f"{r['p95_ms']:.0f}",
                f"{r['fps_per_viewer']:.1f} ({r['fps_min']:.1f})",
                f"{r['mbit_per_viewer']:.1f}",
                f"{r['mpixels_per_s']:.1f}",
                f"{r['mpixels_per_s'] / single['mpixels_per_s']:.2f}x",
                f"{r['mean_scale']:.2f}",
                f"{100 * r['encode_share']:.0f} %",
                f"{r['peak_rss_mib']:.0f}",
            ]
        )
    info = machine_info({"cache": args.cache, "camera path": f"{args.seconds:g} s at {CAMERA_HZ:g} Hz"})
    lines = [
        "# Streaming: latency, frame rate and bandwidth per viewer",
        "",
        "`python bench/stream.py` — a real server, real WebSocket clients on loopback, "
        f"{WIDTH}x{HEIGHT} viewports, cameras moving along an orbit at {CAMERA_HZ:g} Hz. Latency: camera "
        "message sent -> first frame showing it received. Targets: p95 <= 100 ms, >= 16 fps for one viewer, "
        "8 viewers together >= 0.9x one viewer's pixel throughput, idle CPU ~ 0.",
        "",
        *(f"- {k}: {v}" for k, v in info.items()),
        "",
        markdown_table(headers, table),
        "",
        "Idle server (the largest number of viewers connected, their views finished):",
        "",
        markdown_table(
            ["model", "CPU", "RSS MiB"],
            [[m, f"{v['idle_cpu_percent']:.2f} %", f"{v['idle_rss_mib']:.0f}"] for m, v in idle.items()],
        ),
    ]
    out.with_suffix(".md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    plot(rows, out.with_suffix(".png"))


def plot(rows: list[dict[str, Any]], path: Path) -> None:
    plt = pyplot()
    if plt is None:
        return

    fig, (ax_l, ax_f) = plt.subplots(1, 2, figsize=(10, 4))
    for model in dict.fromkeys(r["model"] for r in rows):
        rs = [r for r in rows if r["model"] == model]
        n = [r["viewers"] for r in rs]
        ax_l.plot(n, [r["p50_ms"] for r in rs], "o-", label=f"{model} p50")
        ax_l.plot(n, [r["p95_ms"] for r in rs], "s--", label=f"{model} p95")
        ax_f.plot(n, [r["fps_per_viewer"] for r in rs], "o-", label=model)
    ax_l.axhline(TARGET_P95_MS, color="grey", ls=":", lw=1)
    ax_f.axhline(TARGET_FPS, color="grey", ls=":", lw=1)
    for ax, label in ((ax_l, "input-to-frame latency (ms)"), (ax_f, "frames/s per viewer")):
        ax.set_xlabel("viewers")
        ax.set_ylabel(label)
        ax.set_xscale("log", base=2)
        ax.legend(fontsize=8)
    save_figure(fig, f"streaming {WIDTH}x{HEIGHT}, moving cameras", path)


if __name__ == "__main__":
    sys.exit(main())
