"""The build worker: one process per build job, started by the job manager
(jobs.py) with the 'spawn' method. It runs `vastray.build.build_model` and talks to the
server over a pipe:

    server -> worker   "cancel"
    worker -> server   {"type": "progress", phase, done, total, unit, elapsed, message}
                       {"type": "log", "line": ...}
                       {"type": "done", "report": {...}}
                       {"type": "failed", "error": "..."} | {"type": "cancelled"}

A crash, an out-of-memory kill or a bad input ends this process, never the server; the
server turns whatever happened (a message, an exit status, a signal) into the job's
reason. If the server dies, the worker dies with it (PR_SET_PDEATHSIG), so no orphan
keeps writing into the data directory.
"""

from __future__ import annotations

import ctypes
import signal
import threading
import time
import traceback
from multiprocessing.connection import Connection
from typing import Any

PROGRESS_INTERVAL = 0.1  # seconds between progress messages within a phase


def _die_with_parent() -> None:
    try:
        libc = ctypes.CDLL("libc.so.6", use_errno=True)
        pr_set_pdeathsig = 1
        libc.prctl(pr_set_pdeathsig, signal.SIGKILL)
    except (OSError, AttributeError):
        pass  # not Linux: the server still kills its workers on a clean shutdown


def run(conn: Connection, source: str, output: str, options: dict[str, Any]) -> None:
    """Builds `source` into `output` (a path in the job's own directory)."""
    _die_with_parent()
    # Ctrl-C in the server's terminal reaches the whole process group; the server
    # cancels its jobs itself, so the worker must not die half-way on its own.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    cancel = threading.Event()
    send_lock = threading.Lock()

    def send(message: dict[str, Any]) -> None:
        with send_lock:
            try:
                conn.send(message)
            except (BrokenPipeError, OSError):
                cancel.set()  # the server is gone: stop

    def listen() -> None:
        while True:
            try:
                message = conn.recv()
            except (EOFError, OSError):
                cancel.set()
                return
            if message == "cancel":
                cancel.set()

    threading.Thread(target=listen, name="vastray-build-listener", daemon=True).start()

    from vastray.build import BuildCancelledError, BuildOptions, build_model

    last = {"phase": "", "at": 0.0}

    def progress(p: Any) -> None:
        now = time.monotonic()
        if p.phase != last["phase"]:
            send({"type": "log", "line": f"phase {p.phase} ({p.total:,} {p.unit})"})
        elif now - last["at"] < PROGRESS_INTERVAL and p.done < p.total:
            return
        last.update(phase=p.phase, at=now)
        send(
            {
                "type": "progress",
                "phase": p.phase,
                "done": p.done,
                "total": p.total,
                "unit": p.unit,
                "elapsed": p.elapsed,
                "message": p.message,
            }
        )

    try:
        build_options = BuildOptions(
            memory=int(options["memory"]),
            threads=int(options.get("threads", 0)),
            scratch_dir=options.get("scratch_dir"),
            quantized_splits=bool(options.get("quantized_splits", False)),
            quantized_vertices=bool(options.get("quantized_vertices", False)),
            compact_triangles=bool(options.get("compact_triangles", False)),
            tier_width=float(options.get("tier_width", BuildOptions.tier_width)),
            traversal_cost=float(options.get("traversal_cost", BuildOptions.traversal_cost)),
            lz4_hc_level=int(options.get("lz4_hc_level", 0)),
            voxel_errors=bool(options.get("voxel_errors", False)),
            up=tuple(options["up"]) if options.get("up") else None,
        )
        report = build_model(source, output, build_options, progress=progress, cancel=cancel)
    except BuildCancelledError:
        send({"type": "cancelled"})
    except MemoryError:
        send(
            {"type": "failed", "error": "out of memory (raise the job's memory budget or the server's limit)"}
        )
    except (ValueError, OSError, RuntimeError) as exc:
        # Bad input and I/O problems: the message names the file and what is wrong.
        send({"type": "failed", "error": str(exc)})
    except Exception as exc:  # a bug: say what and where, for the job log
        tail = traceback.format_exc().strip().splitlines()[-6:]
        send({"type": "log", "line": "\n".join(tail)})
        send({"type": "failed", "error": f"internal error: {type(exc).__name__}: {exc}"})
    else:
        send({"type": "done", "report": report})
    finally:
        try:
            conn.close()
        except OSError:
            pass
