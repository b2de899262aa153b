"""`vastray serve` in a child process, for tests, benchmarks and notebooks:
`ServerProcess` starts the console script (as a user would), reads the URL it prints,
waits for /readyz, and stops it with a signal.

    with ServerProcess(Path("data"), "--no-demo") as server:
        client = Client(server.open_url)
"""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import httpx

VASTRAY = Path(sys.executable).parent / "vastray"
URL_LINE = re.compile(r"vastray serving (?P<data>\S+) at (?P<url>http://\S+?)/\?key=(?P<key>\S+)")


class ServerProcess:
    def __init__(
        self,
        data_dir: Path,
        *args: str,
        env: dict[str, str] | None = None,
        key: str | None = None,
        port: int = 0,
    ):
        self.data_dir = data_dir
        self.args = list(args)
        self.env = env or {}
        self.key = key
        self.proc: subprocess.Popen[str] | None = None
        self.log_path = data_dir.parent / f"{data_dir.name}-server.log"
        self.url = ""
        self.port = port

    def start(self, timeout: float = 60.0) -> ServerProcess:
        self.data_dir.mkdir(parents=True, exist_ok=True)
        cmd = [str(VASTRAY), "serve", "--data", str(self.data_dir), "--port", str(self.port), *self.args]
        if self.key is not None:
            cmd += ["--api-key", self.key]
        env = {**os.environ, "PYTHONUNBUFFERED": "1", **self.env}
        log = open(self.log_path, "a")
        self.proc = subprocess.Popen(
            cmd, stdout=subprocess.PIPE, stderr=log, text=True, env=env, start_new_session=True
        )
        deadline = time.monotonic() + timeout
        if self.proc.stdout is None:
            raise RuntimeError("no stdout")
        while time.monotonic() < deadline:
            line = self.proc.stdout.readline()
            if not line:
                raise RuntimeError(f"server exited ({self.proc.wait()}):\n{self.log()}")
            m = URL_LINE.search(line)
            if m:
                self.url = m["url"]
                self.key = m["key"]
                break
        else:
            raise RuntimeError(f"no URL printed within {timeout} s:\n{self.log()}")
        while time.monotonic() < deadline:
            try:
                if httpx.get(f"{self.url}/readyz", timeout=2).status_code == 200:
                    return self
            except httpx.TransportError:
                pass
            time.sleep(0.05)
        raise RuntimeError(f"not ready within {timeout} s:\n{self.log()}")

    def log(self) -> str:
        return self.log_path.read_text() if self.log_path.exists() else ""

    @property
    def pid(self) -> int:
        if self.proc is None:
            raise RuntimeError("not started")
        return self.proc.pid

    def stop(self, sig: int = signal.SIGTERM, timeout: float = 30.0) -> int:
        if self.proc is None or self.proc.poll() is not None:
            return self.proc.returncode if self.proc else 0
        self.proc.send_signal(sig)
        try:
            return self.proc.wait(timeout)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
            raise RuntimeError(f"server did not stop within {timeout} s after {sig}:\n{self.log()}") from None

    def client(self, key: str | None = "default", **kw: Any) -> httpx.Client:
        headers = {}
        use = self.key if key == "default" else key
        if use:
            headers["Authorization"] = f"Bearer {use}"
        return httpx.Client(base_url=self.url, headers=headers, timeout=kw.pop("timeout", 120.0), **kw)

    def workers(self) -> list[int]:
        """Build worker processes of this server (children started by spawn)."""
        pids = []
        for entry in Path("/proc").iterdir():
            if not entry.name.isdigit():
                continue
            try:
                stat = (entry / "stat").read_text()
                cmdline = (entry / "cmdline").read_bytes().decode(errors="replace")
            except OSError:
                continue
            ppid = int(stat.rsplit(")", 1)[1].split()[1])
            if ppid == self.pid and "spawn_main" in cmdline:
                pids.append(int(entry.name))
        return pids

    @property
    def open_url(self) -> str:
        """The URL to open, key included, as the server printed it."""
        return f"{self.url}/?key={self.key}"

    def __enter__(self) -> ServerProcess:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()
