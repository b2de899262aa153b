"""The nginx example (deploy/nginx.conf) for real: nginx on loopback with a self-signed
certificate in front of a real server; the API, a build's server-sent events and a
viewer's WebSocket all go through it."""

from __future__ import annotations

import asyncio
import json
import re
import shutil
import socket
import ssl
import subprocess
import time
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest
import websockets

from vastray.protocol import FrameHeader
from vastray.server.process import ServerProcess

ROOT = Path(__file__).resolve().parents[2]
NGINX = shutil.which("nginx") or "/usr/sbin/nginx"
KEY = "deploy-test-key-0123456789"


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@pytest.fixture(scope="module")
def proxied(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[str, ServerProcess]]:
    if not Path(NGINX).exists():
        pytest.fail("nginx is not installed (make system-deps installs it)")
    tmp = tmp_path_factory.mktemp("nginx")
    server = ServerProcess(tmp / "data", "--no-demo", key=KEY).start()
    cert, key = tmp / "cert.pem", tmp / "key.pem"
    subprocess.run(
        [
            "openssl",
            "req",
            "-x509",
            "-newkey",
            "rsa:2048",
            "-nodes",
            "-days",
            "1",
            "-subj",
            "/CN=localhost",
            "-keyout",
            str(key),
            "-out",
            str(cert),
        ],
        check=True,
        capture_output=True,
    )
    https_port, http_port = free_port(), free_port()
    site = (ROOT / "deploy" / "nginx.conf").read_text()
    site = site.replace("server 127.0.0.1:8000;", f"server 127.0.0.1:{httpx.URL(server.url).port};")
    site = site.replace("listen 443 ssl http2;", f"listen 127.0.0.1:{https_port} ssl http2;")
    site = site.replace("listen 80;", f"listen 127.0.0.1:{http_port};")
    site = site.replace("/etc/ssl/certs/vastray.pem", str(cert)).replace(
        "/etc/ssl/private/vastray.key", str(key)
    )
    assert str(cert) in site and f":{https_port} ssl" in site, "the example's placeholders changed"
    (tmp / "site.conf").write_text(site)
    (tmp / "logs").mkdir()
    main = f"""
pid {tmp}/nginx.pid;
error_log {tmp}/logs/error.log;
events {{}}
http {{
    access_log {tmp}/logs/access.log;
    client_body_temp_path {tmp}/body; proxy_temp_path {tmp}/proxy;
    fastcgi_temp_path {tmp}/fcgi; uwsgi_temp_path {tmp}/uwsgi; scgi_temp_path {tmp}/scgi;
    include {tmp}/site.conf;
}}
"""
    (tmp / "nginx.conf").write_text(main)
    check = subprocess.run(
        [NGINX, "-t", "-p", str(tmp), "-c", str(tmp / "nginx.conf")], capture_output=True, text=True
    )
    assert check.returncode == 0, check.stderr
    proc = subprocess.Popen([NGINX, "-p", str(tmp), "-c", str(tmp / "nginx.conf"), "-g", "daemon off;"])
    base = f"https://localhost:{https_port}"
    for _ in range(100):
        try:
            if httpx.get(f"{base}/healthz", verify=False, timeout=1).status_code == 200:
                break
        except httpx.TransportError:
            time.sleep(0.05)
    try:
        yield base, server
    finally:
        proc.terminate()
        proc.wait(10)
        server.stop()


def test_api_and_build_events_through_nginx(proxied: tuple[str, ServerProcess]) -> None:
    base, _ = proxied
    with httpx.Client(base_url=base, verify=False, headers={"Authorization": f"Bearer {KEY}"}) as api:
        assert api.get("/readyz").json()["status"] == "ready"
        job = api.post("/api/jobs", json={"source": "scene:spheres:6000:1"}).json()
        kinds = []
        with api.stream("GET", f"/api/jobs/{job['id']}/events", params={"key": KEY}, timeout=120) as r:
            for line in r.iter_lines():
                if line.startswith("event: "):
                    kinds.append(line[7:])
                    if kinds[-1] == "end":
                        break
        assert kinds[0] == "progress" and kinds[-1] == "end"
        assert api.get(f"/api/jobs/{job['id']}").json()["state"] == "succeeded"
        page = api.get("/")
        assert page.status_code == 200 and "<canvas" in page.text
        assert re.search(r"/ui/js/main\.js", page.text) and api.get("/ui/js/main.js").status_code == 200


def test_a_viewer_streams_through_nginx(proxied: tuple[str, ServerProcess]) -> None:
    base, _ = proxied
    with httpx.Client(base_url=base, verify=False, headers={"Authorization": f"Bearer {KEY}"}) as api:
        job = api.post("/api/jobs", json={"source": "scene:plant:8000:2"}).json()
        while (info := api.get(f"/api/jobs/{job['id']}").json())["state"] in ("queued", "running"):
            time.sleep(0.1)
        assert info["state"] == "succeeded"
    context = ssl.create_default_context()
    context.check_hostname = False
    context.verify_mode = ssl.CERT_NONE

    async def view() -> FrameHeader:
        url = base.replace("https://", "wss://") + "/api/stream"
        async with websockets.connect(url, ssl=context) as ws:
            await ws.send(
                json.dumps(
                    {
                        "type": "hello",
                        "protocol": 1,
                        "model": info["model_id"],
                        "token": KEY,
                        "viewport": {"width": 160, "height": 120},
                    }
                )
            )
            while True:
                m = await asyncio.wait_for(ws.recv(), 60)
                if isinstance(m, bytes):
                    h = FrameHeader.unpack(m)
                    await ws.send(json.dumps({"type": "ack", "frame": h.frame}))
                    if h.final:
                        return h

    final = asyncio.run(view())
    assert final.complete and final.width == 160
