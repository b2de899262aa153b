"""Build jobs: a queue, a bounded number of worker processes, progress, cancellation.

Each job builds in its own process (build_worker.py) into its own directory
`jobs/<id>/` (scratch files and the partial model), so a crash, an out-of-memory kill
or a bad input fails that job alone, and whatever it leaves is removed with the
directory. Only a complete model is moved into `models/` and published.

A runner thread per concurrency slot takes queued jobs, starts their worker, reads its
messages, watches its resident memory, and writes the job's state to the registry;
listeners (server-sent events, viewers) get a snapshot after every change.
"""

from __future__ import annotations

import asyncio
import logging
import multiprocessing
import queue
import shutil
import signal
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from vastray.build import STATED_OVERHEAD_BYTES
from vastray.schemas import TERMINAL_JOB_STATES, JobInfo
from vastray.server import build_worker
from vastray.server.registry import JobRow, Registry

log = logging.getLogger("vastray.jobs")

# Where each phase's progress lands in the job's percent (the build phases' usual share
# of the time: bench/results/build.md).
PHASE_SPAN = {"read": (0.0, 20.0), "split": (20.0, 30.0), "build": (30.0, 92.0), "write": (92.0, 100.0)}
REGISTRY_WRITE_INTERVAL = 0.25  # seconds between progress writes of one job
CANCEL_GRACE = 5.0  # seconds a cancelled worker gets to clean up before it is killed


def resident_bytes(pid: int) -> int | None:
    try:
        with open(f"/proc/{pid}/status") as f:
            for line in f:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        return None
    return None


def overall_percent(phase: str, done: int, total: int) -> float:
    lo, hi = PHASE_SPAN.get(phase, (0.0, 100.0))
    return lo + (hi - lo) * (min(done, total) / total if total > 0 else 0.0)


@dataclass
class _Running:
    job_id: str
    cancel_requested: threading.Event = field(default_factory=threading.Event)
    process: Any = None
    reason: str | None = None  # why the server ended it (cancel, shutdown, memory)


class JobManager:
    def __init__(
        self,
        registry: Registry,
        data_dir: Path,
        *,
        concurrency: int,
        rss_slack: float,
        publish: Callable[[JobRow, Path, dict[str, Any]], str | None],
        discard: Callable[[JobRow], None],
    ) -> None:
        self.registry = registry
        self.jobs_dir = data_dir / "jobs"
        self.jobs_dir.mkdir(parents=True, exist_ok=True)
        self.concurrency = max(1, concurrency)
        # A worker may use its budget and the builder's stated fixed overhead (the builder
        # keeps within both by design) times this slack before the watchdog stops it.
        self.rss_slack = rss_slack
        self._publish = publish
        self._discard = discard
        self._queue: queue.Queue[str | None] = queue.Queue()
        self._running: dict[str, _Running] = {}
        self._lock = threading.Lock()
        self._listeners: dict[str, set[asyncio.Queue[JobInfo]]] = {}
        self._any_listeners: set[asyncio.Queue[JobInfo]] = set()
        self._loop: asyncio.AbstractEventLoop | None = None
        self._threads: list[threading.Thread] = []
        self._stopping = threading.Event()
        self._ctx = multiprocessing.get_context("spawn")

    # -- lifecycle -------------------------------------------------------------------------

    def start(self, loop: asyncio.AbstractEventLoop) -> None:
        self._loop = loop
        # Directories of jobs that are not queued are leftovers of a crash: remove them.
        active = {j.id for j in self.registry.jobs(("queued", "running"))}
        for d in self.jobs_dir.iterdir():
            if d.name not in active:
                shutil.rmtree(d, ignore_errors=True)
        for job in reversed(self.registry.jobs(("queued",))):
            self._queue.put(job.id)
        for slot in range(self.concurrency):
            t = threading.Thread(target=self._runner, name=f"vastray-jobs-{slot}", daemon=True)
            t.start()
            self._threads.append(t)

    def shutdown(self, timeout: float = 10.0) -> None:
        """Cancels what runs, marks it interrupted, leaves nothing half-written."""
        self._stopping.set()
        with self._lock:
            running = list(self._running.values())
        for r in running:
            r.reason = "interrupted: the server shut down"
            r.cancel_requested.set()
        for job in self.registry.jobs(("queued",)):
            self._finish(job.id, "interrupted", error="interrupted: the server shut down before it started")
        for _ in self._threads:
            self._queue.put(None)
        deadline = time.monotonic() + timeout
        for t in self._threads:
            t.join(max(0.0, deadline - time.monotonic()))

    # -- requests --------------------------------------------------------------------------

    def submit(self, job: JobRow) -> JobInfo:
        self.registry.add_job(job)
        self.log(
            job.id,
            f"queued: build {job.source} (memory {job.options['memory'] >> 20} MiB, "
            f"threads {job.options.get('threads', 0) or 'all'})",
        )
        self._queue.put(job.id)
        info = self.info(job.id)
        self._notify(info)
        return info

    def cancel(self, job_id: str) -> JobInfo:
        job = self.registry.job(job_id)
        if job is None:
            raise KeyError(job_id)
        if job.state in TERMINAL_JOB_STATES:
            return self.info(job_id)
        with self._lock:
            running = self._running.get(job_id)
            if running is not None:
                running.reason = "cancelled on request"
                running.cancel_requested.set()
                return self.info(job_id)
        # Queued: it never starts.
        self._finish(job_id, "cancelled", error="cancelled on request before it started")
        return self.info(job_id)

    def info(self, job_id: str) -> JobInfo:
        job = self.registry.job(job_id)
        if job is None:
            raise KeyError(job_id)
        return JobInfo(
            id=job.id,
            kind="build",
            model_id=job.model_id,
            name=job.name,
            source=job.source,
            state=job.state,
            phase=job.phase,
            percent=job.percent,
            eta_seconds=job.eta_seconds,
            message=job.message,
            error=job.error,
            options=job.options,
            report=job.report,
            created_at=job.created_at,
            started_at=job.started_at,
            finished_at=job.finished_at,
            log_tail=self.registry.job_log(job_id, 20),
        )

    def log(self, job_id: str, *lines: str) -> None:
        for line in lines:
            log.info("job %s: %s", job_id, line)
        self.registry.append_log(job_id, list(lines))

    def worker_pid(self, job_id: str) -> int | None:
        with self._lock:
            r = self._running.get(job_id)
            return r.process.pid if r is not None and r.process is not None else None

    # -- listeners (async side) ------------------------------------------------------------

    def listen(self, job_id: str | None = None) -> asyncio.Queue[JobInfo]:
        """A queue that receives a snapshot of the job (or of every job, for None)
        after each change. Call `unlisten` when done."""
        q: asyncio.Queue[JobInfo] = asyncio.Queue(maxsize=256)
        if job_id is None:
            self._any_listeners.add(q)
        else:
            self._listeners.setdefault(job_id, set()).add(q)
        return q

    def unlisten(self, q: asyncio.Queue[JobInfo], job_id: str | None = None) -> None:
        if job_id is None:
            self._any_listeners.discard(q)
        else:
            self._listeners.get(job_id, set()).discard(q)

    def _notify(self, info: JobInfo) -> None:
        loop = self._loop
        if loop is None or loop.is_closed():
            return

        def deliver() -> None:
            for q in [*self._listeners.get(info.id, ()), *self._any_listeners]:
                if q.full():  # a listener that does not read loses old snapshots, not new ones
                    q.get_nowait()
                q.put_nowait(info)

        try:
            loop.call_soon_threadsafe(deliver)
        except RuntimeError:
            pass  # the loop closed during shutdown

    # -- runners (threads) -----------------------------------------------------------------

    def _runner(self) -> None:
        while True:
            job_id = self._queue.get()
            if job_id is None or self._stopping.is_set():
                return
            job = self.registry.job(job_id)
            if job is None or job.state != "queued":
                continue
            try:
                self._run(job)
            except Exception as exc:  # never lose a runner to a bug in one job
                log.exception("job %s: runner failed", job_id)
                self._finish(job_id, "failed", error=f"internal error: {exc}")

    def _run(self, job: JobRow) -> None:
        workdir = self.jobs_dir / job.id
        workdir.mkdir(parents=True, exist_ok=True)
        output = workdir / "model.vast"
        options = dict(job.options)
        options["scratch_dir"] = str(workdir)
        running = _Running(job.id)
        parent, child = self._ctx.Pipe()
        process = self._ctx.Process(
            target=build_worker.run,
            args=(child, job.source, str(output), options),
            name=f"vastray-build-{job.id}",
            daemon=True,
        )
        with self._lock:
            self._running[job.id] = running
        started = time.time()
        try:
            process.start()
            child.close()
            running.process = process
            self.registry.update_job(
                job.id, state="running", started_at=started, phase="starting", percent=0.0
            )
            self.log(job.id, f"started in worker process {process.pid}")
            self._notify(self.info(job.id))
            outcome = self._supervise(job, running, parent, process)
        finally:
            parent.close()
            if process.is_alive():
                process.kill()
            process.join(5.0)
            with self._lock:
                self._running.pop(job.id, None)
        state, error, report = outcome
        if state == "succeeded":
            try:
                published = self._publish(job, output, report or {})
                if report is not None:
                    # Where the model is now (the worker wrote it into the job's directory).
                    report["output"] = published
            except Exception as exc:
                log.exception("job %s: publishing failed", job.id)
                state, error = "failed", f"the built model could not be registered: {exc}"
        shutil.rmtree(workdir, ignore_errors=True)
        if state != "succeeded":
            self._discard(job)
        self._finish(job.id, state, error=error, report=report)

    def _supervise(
        self, job: JobRow, running: _Running, conn: Any, process: Any
    ) -> tuple[str, str | None, dict[str, Any] | None]:
        limit = int(self.rss_slack * (int(job.options["memory"]) + STATED_OVERHEAD_BYTES))
        last_write = 0.0
        cancel_sent_at: float | None = None
        result: tuple[str, str | None, dict[str, Any] | None] | None = None
        phase, percent = "starting", 0.0
        supervised_since = time.monotonic()
        while True:
            if running.cancel_requested.is_set() and cancel_sent_at is None:
                cancel_sent_at = time.monotonic()
                try:
                    conn.send("cancel")
                except (BrokenPipeError, OSError):
                    pass
                self.log(job.id, running.reason or "cancel requested")
            if cancel_sent_at is not None and time.monotonic() - cancel_sent_at > CANCEL_GRACE:
                process.kill()
            rss = resident_bytes(process.pid) if process.pid else None
            if rss is not None and rss > limit and result is None:
                process.kill()
                running.reason = (
                    f"killed: resident memory {rss >> 20} MiB exceeded the job's limit of {limit >> 20} MiB "
                    f"(budget {int(job.options['memory']) >> 20} MiB + overhead)"
                )
                self.log(job.id, running.reason)
            try:
                ready = conn.poll(0.2)
            except (EOFError, OSError):
                ready = False
            if ready:
                try:
                    message = conn.recv()
                except (EOFError, OSError):
                    message = None
                if message is not None:
                    kind = message.get("type")
                    if kind == "progress":
                        new_phase = message["phase"] != phase
                        phase = message["phase"]
                        percent = overall_percent(phase, message["done"], message["total"])
                        now = time.monotonic()
                        if new_phase or now - last_write >= REGISTRY_WRITE_INTERVAL:
                            last_write = now
                            elapsed = now - supervised_since
                            eta = elapsed * (100.0 - percent) / percent if percent > 0.5 else None
                            self.registry.update_job(
                                job.id,
                                phase=phase,
                                percent=percent,
                                eta_seconds=eta,
                                message=message.get("message") or None,
                            )
                            self._notify(self.info(job.id))
                    elif kind == "log":
                        self.log(job.id, message["line"])
                    elif kind == "done":
                        result = ("succeeded", None, message["report"])
                    elif kind == "cancelled":
                        state = "interrupted" if self._stopping.is_set() else "cancelled"
                        result = (state, running.reason or "cancelled", None)
                    elif kind == "failed":
                        result = ("failed", message["error"], None)
                    continue
            if not process.is_alive():
                process.join(1.0)
                break
        if result is not None and not (result[0] == "succeeded" and process.exitcode not in (0, None)):
            return result
        # No verdict from the worker: say how it ended.
        code = process.exitcode
        if running.reason is not None and running.reason.startswith("killed"):
            return ("failed", running.reason, None)
        if running.cancel_requested.is_set():
            state = "interrupted" if self._stopping.is_set() else "cancelled"
            return (state, running.reason or "cancelled", None)
        if code is not None and code < 0:
            name = signal.Signals(-code).name if -code in signal.Signals._value2member_map_ else str(-code)
            hint = " (the system may have run out of memory)" if -code == signal.SIGKILL else ""
            return ("failed", f"the build worker was killed by {name}{hint}", None)
        return ("failed", f"the build worker exited with status {code} without a result", None)

    def _finish(
        self, job_id: str, state: str, *, error: str | None = None, report: dict[str, Any] | None = None
    ) -> None:
        fields: dict[str, Any] = {
            "state": state,
            "finished_at": time.time(),
            "error": error,
            "eta_seconds": None,
        }
        if state == "succeeded":
            fields.update(percent=100.0, phase="done")
        if report is not None:
            fields["report"] = _jsonable(report)
        self.registry.update_job(job_id, **fields)
        if state == "succeeded" and report:
            self.log(
                job_id,
                f"succeeded: {report.get('triangles', 0):,} triangles in "
                f"{report.get('seconds', 0.0):.1f} s "
                f"({report.get('triangles_per_second', 0.0) / 1e6:.2f} Mtri/s)",
            )
            for warning in report.get("warnings", []):
                self.log(job_id, f"warning: {warning}")
        elif state != "succeeded":
            self.log(job_id, f"{state}: {error}")
        self._notify(self.info(job_id))


def _jsonable(value: Any) -> Any:
    if isinstance(value, dict):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, (str, int, float, bool)) or value is None:
        return value
    if hasattr(value, "item"):  # numpy scalars
        return value.item()
    return str(value)
