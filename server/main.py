"""`vastray serve`: uvicorn on a socket we bind ourselves (so port 0 works and the URL
printed is the real one), with the URL to open, key included, printed as Jupyter does.

On SIGINT/SIGTERM uvicorn stops accepting; before it waits for open connections we set
the app's `stopping` event, so event streams and viewers end at once; then the
lifespan cancels running jobs (marked interrupted) and removes their partial output.
"""

from __future__ import annotations

import asyncio
import logging
import socket
import sys
from types import FrameType

import uvicorn

from vastray.server.app import State, create_app
from vastray.server.settings import Settings

log = logging.getLogger("vastray.server")


class _Server(uvicorn.Server):
    def __init__(self, config: uvicorn.Config, state: State) -> None:
        super().__init__(config)
        self.state = state
        self.loop: asyncio.AbstractEventLoop | None = None

    async def serve(self, sockets: list[socket.socket] | None = None) -> None:
        self.loop = asyncio.get_running_loop()
        await super().serve(sockets)

    async def shutdown(self, sockets: list[socket.socket] | None = None) -> None:
        # Tell viewers why before uvicorn closes their sockets with a bare close code.
        self.state.stopping.set()
        await self.state.streams.close_all("the server is shutting down")
        await super().shutdown(sockets)

    def handle_exit(self, sig: int, frame: FrameType | None) -> None:
        if self.loop is not None and not self.loop.is_closed():
            self.loop.call_soon_threadsafe(self.state.stopping.set)
        super().handle_exit(sig, frame)
        # uvicorn raises the signal again once it has shut down, so the process dies of
        # it; a shutdown that was asked for and went cleanly exits 0 instead.
        self._captured_signals.clear()


def url_to_open(settings: Settings, port: int, key: str | None) -> str:
    if settings.public_url:
        base = settings.public_url.rstrip("/")
    else:
        host = settings.host
        shown = "127.0.0.1" if host in ("0.0.0.0", "") else ("[::1]" if host == "::" else host)
        base = f"http://{shown}:{port}"
    return f"{base}/?key={key}" if key else f"{base}/"


def listening_socket(host: str, port: int) -> socket.socket:
    """The server's socket, bound. TCP_NODELAY is set on it because connections accepted
    from it inherit it (Linux, the BSDs) and uvloop's transports do not set it: without
    it, Nagle's algorithm held each frame's stats event (and small frames behind it)
    until the client's delayed ACK, 40 ms later."""
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    sock = socket.socket(family, socket.SOCK_STREAM)
    try:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        sock.bind((host, port))
    except OSError:
        sock.close()
        raise
    return sock


def serve(settings: Settings) -> int:
    logging.basicConfig(
        level=logging.INFO, format="%(asctime)s %(levelname)-7s %(name)s: %(message)s", stream=sys.stderr
    )
    try:
        sock = listening_socket(settings.host, settings.port)
    except OSError as exc:
        print(
            f"vastray: error: cannot listen on {settings.host}:{settings.port}: {exc.strerror}",
            file=sys.stderr,
        )
        return 2
    port = sock.getsockname()[1]
    app = create_app(settings)
    state: State = app.state.vastray
    config = uvicorn.Config(
        app,
        log_level="info",
        timeout_graceful_shutdown=10,
        ws_ping_interval=settings.ws_ping_interval,
        ws_ping_timeout=settings.ws_ping_interval,
        ws_max_size=settings.max_message_bytes,
        proxy_headers=True,
        access_log=False,
    )
    server = _Server(config, state)
    key = state.auth.primary_key
    url = url_to_open(settings, port, key)
    origin = "made at random for this run" if state.auth.generated else "configured"
    # One line a script can read: the URL with its key.
    print(f"vastray serving {state.data_dir} at {url}", flush=True)
    print(f"  API key ({origin}); API docs at {url.split('?')[0]}docs", flush=True)
    asyncio.run(server.serve(sockets=[sock]))
    return 0
