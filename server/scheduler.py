"""The render scheduler: which view renders next, on the shared native thread pool.

- **Fair.** Every view keeps a virtual time: the render and encode seconds it has used.
  The view that has used least goes next (the rule of Linux's CFS scheduler), so a heavy
  view of one model cannot starve a light view of another: each gets an equal share of
  the render time, and a light view's frames come between the heavy one's. A view that
  joins starts at the smallest virtual time of the others, so it gets no burst.
- **Budgets.** A moving view's frames are held to a frame-time budget, its target frame
  rate's interval divided among the views moving at once, times a gain that grows (up to
  the frames in flight, whose wall times overlap) while the view's measured rate is over
  its target; its quality controller trades resolution (then accuracy) to keep within it.
- **Only useful work.** A view renders when it has something to show (a new camera,
  a refinement pass, blocks that arrived for an incomplete pass) and one of its
  subscribers can take a frame (backpressure); a still, finished view costs nothing.
- **Never on the event loop.** Renders and encodes run on the render executor; block
  arrivals are watched by a thread that sleeps unless some view waits for data.

A frame is one whole frame: the native pool renders one frame at a time with every core
(its tiles spread over the lanes), and `workers` jobs in flight let one frame encode
while the next renders.
"""

from __future__ import annotations

import asyncio
import logging
import threading
import time
from collections.abc import Callable
from concurrent.futures import Executor

from vastray import native
from vastray.server.views import RenderedFrame, RenderJob, View

log = logging.getLogger("vastray.scheduler")


class Scheduler:
    def __init__(self, cache: native.BlockCache, executor: Executor, workers: int,
                 deliver: Callable[[View, RenderedFrame, str | None], None]) -> None:  # fmt: skip
        self.cache = cache
        self.executor = executor
        self.workers = max(1, workers)
        self.deliver = deliver
        self.views: set[View] = set()
        # Views removed while a frame of theirs was rendering, with what to do once it is
        # done (release the model: it must stay open until no frame uses it).
        self._leaving: dict[View, Callable[[], None]] = {}
        self.running = 0
        self._wake: asyncio.Event | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._task: asyncio.Task[None] | None = None
        self._timer: asyncio.TimerHandle | None = None
        self._watch = threading.Event()  # set while some view waits for blocks
        self._stop = threading.Event()
        self._watcher: threading.Thread | None = None

    # -- lifecycle -------------------------------------------------------------------------

    def start(self) -> None:
        self._loop = asyncio.get_running_loop()
        self._wake = asyncio.Event()
        self._task = asyncio.create_task(self._dispatch(), name="vastray-scheduler")
        self._watcher = threading.Thread(target=self._watch_blocks, name="vastray-block-watcher", daemon=True)
        self._watcher.start()

    async def stop(self) -> None:
        self._stop.set()
        self._watch.set()
        if self._task is not None:
            self._task.cancel()
            try:
                await self._task
            except asyncio.CancelledError:
                pass
        if self._watcher is not None:
            await asyncio.to_thread(self._watcher.join, 5.0)

    # -- views -----------------------------------------------------------------------------

    def add(self, view: View) -> None:
        others = [v.vtime for v in self.views]
        view.vtime = min(others) if others else 0.0
        # A new view of a model others move through starts at the coarsest of their
        # moving scales, not at full resolution: its first frames then fit its share.
        scales = [v.controller.scale for v in self.views if v.model_id == view.model_id]
        if scales:
            view.controller.scale = min(scales)
        self.views.add(view)
        self.notify()

    def remove(self, view: View, then: Callable[[], None] | None = None) -> None:
        """Takes the view out of the schedule; `then` runs once no frame of the view is
        rendering any more: now, or when the frame in flight is done."""
        self.views.discard(view)
        if then is not None:
            if view.busy:
                self._leaving[view] = then
            else:
                then()
        self.notify()

    def _left(self, view: View) -> None:
        then = self._leaving.pop(view, None)
        if then is not None:
            then()

    def notify(self) -> None:
        """Something changed (a camera, an ack, a new view): look again."""
        if self._wake is not None:
            self._wake.set()

    @property
    def moving(self) -> int:
        return sum(1 for v in self.views if v.phase == "moving")

    # -- dispatch --------------------------------------------------------------------------

    async def _dispatch(self) -> None:
        assert self._wake is not None and self._loop is not None
        while True:
            await self._wake.wait()
            self._wake.clear()
            self._start_ready()

    def _arrivals(self) -> int:
        """Blocks the fetchers have finished so far (read or failed): the block-arrival
        count a view that waits for data compares with its last frame's. Counted where the
        fetch ends, not when a frame publishes the block or the watcher wakes: a view whose
        blocks arrive before its frame is taken back, or are published by another view's
        frame, must still see them arrive."""
        t = self.cache.totals()
        return int(t["bytes_read"]) + int(t["failed"])

    def _start_ready(self) -> None:
        assert self._loop is not None
        now = time.monotonic()
        arrivals = self._arrivals()
        next_wake: float | None = None
        waiting_for_data = False
        candidates: list[tuple[float, View, RenderJob]] = []
        moving = max(1, self.moving)
        # Frames in flight overlap: a view's budget may grow up to this many shares of the
        # interval while its measured rate stays over its target (QualityController.gain).
        in_flight = min(self.workers, moving)
        for view in self.views:
            if view.waiting_for_data and view.phase != "idle":
                waiting_for_data = True
            if view.busy or not view.wants_frame():
                continue
            view.max_gain = in_flight
            budget = min(view.controller.gain, in_flight) / (view.quality.target_fps * moving)
            job = view.next_job(now, arrivals, budget)
            if isinstance(job, float):
                next_wake = job if next_wake is None else min(next_wake, job)
            elif job is not None:
                candidates.append((view.vtime, view, job))
        if waiting_for_data:
            self._watch.set()
        else:
            self._watch.clear()
        candidates.sort(key=lambda c: c[0])
        for _, view, job in candidates:
            if self.running >= self.workers:
                break
            self._launch(view, job)
        if next_wake is not None:
            if self._timer is not None:
                self._timer.cancel()
            self._timer = self._loop.call_later(max(0.001, next_wake), self.notify)

    def _launch(self, view: View, job: RenderJob) -> None:
        assert self._loop is not None
        view.busy = True
        self.running += 1
        arrivals = self._arrivals()  # before the frame: what arrives later is news to it
        future = self._loop.run_in_executor(self.executor, view.render, job)
        future.add_done_callback(lambda f: self._done(view, job, f, arrivals))

    def _done(self, view: View, job: RenderJob, future: asyncio.Future[RenderedFrame], arrivals: int) -> None:
        self.running -= 1
        try:
            result = future.result()
        except Exception as exc:
            view.busy = False
            self._left(view)
            log.exception("view %s: render failed", view.id)
            self.deliver(view, None, f"render failed: {exc}")  # type: ignore[arg-type]
            self.notify()
            return
        view.vtime += result.finished_at - result.started_at
        frame, warning = view.finish(job, result, arrivals)
        self._left(view)
        if frame is not None or warning is not None:
            self.deliver(view, frame, warning)  # type: ignore[arg-type]
        self.notify()

    # -- block arrivals (a thread) ---------------------------------------------------------

    def _watch_blocks(self) -> None:
        while not self._stop.is_set():
            if not self._watch.wait(1.0):
                continue
            if self._stop.is_set():
                return
            # Returns at once (False) when nothing is pending; then the next frame, not
            # this thread, will find out what is missing.
            arrived = self.cache.wait_for_fetches(200.0)
            if not arrived:
                time.sleep(0.02)
                continue
            loop = self._loop
            if loop is None or loop.is_closed():
                return
            try:
                loop.call_soon_threadsafe(self._blocks_arrived)
            except RuntimeError:
                return

    def _blocks_arrived(self) -> None:
        self.notify()
