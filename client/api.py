"""The REST side of the Python client, asynchronous (httpx). `vastray.client.Client`
is the same API, blocking, for scripts and notebooks."""

from __future__ import annotations

import json
import os
import time
from collections.abc import AsyncIterator, Callable, Iterable, Sequence
from pathlib import Path
from typing import Any
from urllib.parse import parse_qs, urlsplit, urlunsplit

import httpx

from vastray.client.frames import Frame, decode_image
from vastray.protocol import CameraState
from vastray.schemas import (
    TERMINAL_JOB_STATES,
    JobInfo,
    ModelInfo,
    PartInfo,
    PickHit,
    SectionPlane,
    TokenInfo,
    UploadInfo,
)

# A section plane as the client takes it: (nx, ny, nz, offset), or a SectionPlane
# (`vastray.schemas.section_box` gives six); geometry where n . p + offset < 0 is cut.
Plane = tuple[float, float, float, float] | SectionPlane


def section_planes(planes: Sequence[Plane]) -> list[dict[str, Any]]:
    """Planes as the API's `sections` field and the stream's message take them."""
    out: list[dict[str, Any]] = []
    for p in planes:
        out.append(p.model_dump() if isinstance(p, SectionPlane) else {"normal": [*p[:3]], "offset": p[3]})
    return out


UPLOAD_CHUNK = 1 << 20


class VastrayError(Exception):
    """An error the server reported: its HTTP status, code and message. Status 0: not
    an HTTP answer (an error over the stream, a failed job, a refusal by the client)."""

    def __init__(self, status: int, code: str, message: str) -> None:
        super().__init__(f"{message} ({status} {code})" if status else f"{message} ({code})")
        self.status = status
        self.code = code
        self.message = message


class BuildFailedError(VastrayError):
    """A build job ended without a model; `job` says how and why."""

    def __init__(self, job: JobInfo) -> None:
        super().__init__(0, job.state, f"build {job.id} {job.state}: {job.error}")
        self.job = job


def split_url(url: str) -> tuple[str, str | None]:
    """(base URL, key) of a URL as `vastray serve` prints it: http://host:port/?key=…"""
    parts = urlsplit(url)
    query = parse_qs(parts.query)
    key = (query.get("key") or query.get("token") or [None])[0]
    return urlunsplit((parts.scheme, parts.netloc, parts.path.rstrip("/"), "", "")), key


def raise_for_error(r: httpx.Response) -> None:
    if r.is_success:
        return
    try:
        error = r.json()["error"]
        code, message = error["code"], error["message"]
    except (ValueError, KeyError, TypeError):
        code, message = "http_error", r.text[:500] or r.reason_phrase
    raise VastrayError(r.status_code, code, message)


def _model_id(model: str | ModelInfo) -> str:
    return model.id if isinstance(model, ModelInfo) else model


class AsyncClient:
    """The render service from asyncio code.

    async with AsyncClient("http://127.0.0.1:8000/?key=…") as vr:
        job = await vr.build("scene:plant:1e6:3")
        await vr.wait(job)
        frame = await vr.render(job.model_id, camera={"width": 1280, "height": 720})
    """

    def __init__(self, url: str | None = None, *, key: str | None = None, timeout: float = 120.0) -> None:
        url = url or os.environ.get("VASTRAY_URL", "http://127.0.0.1:8000")
        base, url_key = split_url(url)
        self.url = base
        self.key = key or url_key or os.environ.get("VASTRAY_KEY")
        # A review's join (or presenter) link names its review: `join()` joins that one.
        self.review_id: str | None = (parse_qs(urlsplit(url).query).get("review") or [None])[0]
        headers = {"Authorization": f"Bearer {self.key}"} if self.key else {}
        self._http = httpx.AsyncClient(base_url=base, headers=headers, timeout=timeout)

    async def __aenter__(self) -> AsyncClient:
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.aclose()

    async def aclose(self) -> None:
        await self._http.aclose()

    async def _json(self, method: str, path: str, **kw: Any) -> Any:
        r = await self._http.request(method, path, **kw)
        raise_for_error(r)
        return r.json() if r.content else None

    # -- models ----------------------------------------------------------------------------

    async def health(self) -> dict[str, Any]:
        return dict(await self._json("GET", "/readyz"))

    async def models(self) -> list[ModelInfo]:
        return [ModelInfo(**m) for m in await self._json("GET", "/api/models")]

    async def model(self, model: str | ModelInfo) -> ModelInfo:
        return ModelInfo(**await self._json("GET", f"/api/models/{_model_id(model)}"))

    async def parts(
        self,
        model: str | ModelInfo,
        query: str = "",
        *,
        ids: Iterable[int] | None = None,
        limit: int = 20_000,
    ) -> list[PartInfo]:
        """The model's parts whose name contains `query` (ignoring case); with `ids`, only
        those of the parts with these ids (unknown ids are left out)."""
        params: dict[str, Any] = {"q": query, "limit": limit}
        if ids is not None:
            wanted = sorted({int(i) for i in ids})
            if not wanted:
                return []
            params["ids"] = ",".join(map(str, wanted))
        found = await self._json("GET", f"/api/models/{_model_id(model)}/parts", params=params)
        return [PartInfo(**p) for p in found["parts"]]

    async def upload(
        self,
        path: str | Path,
        *,
        name: str | None = None,
        register: bool = True,
        up: tuple[float, float, float] | None = None,
    ) -> UploadInfo:
        """Uploads a mesh or a built model, streamed from disk. With `register` a built
        model is served at once and a mesh starts its build (see `.created`); `up` says
        which way is up in it (default +y; a z-up mesh takes (0, 0, 1))."""
        path = Path(path)

        async def chunks() -> AsyncIterator[bytes]:
            with open(path, "rb") as f:
                while chunk := f.read(UPLOAD_CHUNK):
                    yield chunk

        params: dict[str, Any] = {"filename": path.name, "register": str(register).lower()}
        if name:
            params["name"] = name
        if up is not None:
            params["up"] = ",".join(repr(float(c)) for c in up)
        r = await self._http.post(
            "/api/uploads",
            params=params,
            content=chunks(),
            headers={"content-length": str(path.stat().st_size)},
        )
        raise_for_error(r)
        return UploadInfo(**r.json())

    async def register(
        self, path: str, *, name: str | None = None, up: tuple[float, float, float] | None = None
    ) -> tuple[ModelInfo, JobInfo | None]:
        """A file already in the server's data directory (relative path)."""
        out = await self._json("POST", "/api/models", json={"path": path, "name": name, "up": up})
        return ModelInfo(**out["model"]), JobInfo(**out["job"]) if out.get("job") else None

    async def update_model(
        self,
        model: str | ModelInfo,
        *,
        name: str | None = None,
        up: tuple[float, float, float] | None = None,
        units: str | None = None,
    ) -> ModelInfo:
        """Renames a model, says which way is up in it (views opened after this start
        upright: a z-up scan takes `up=(0, 0, 1)`), or the length unit of its coordinates
        ("mm", "cm", "m", "km", "in", "ft"; "" for none)."""
        body = {k: v for k, v in (("name", name), ("up", up), ("units", units)) if v is not None}
        return ModelInfo(**await self._json("PATCH", f"/api/models/{_model_id(model)}", json=body))

    async def delete(self, model: str | ModelInfo) -> bool:
        """True if deleted now, False if it goes when its last viewer leaves."""
        r = await self._http.delete(f"/api/models/{_model_id(model)}")
        raise_for_error(r)
        return r.status_code == 204

    async def token(self, model: str | ModelInfo, *, ttl: float = 86400.0, label: str | None = None) -> str:
        """A viewing token for one model (what a review link carries)."""
        out = await self._json(
            "POST", f"/api/models/{_model_id(model)}/tokens", json={"ttl_seconds": ttl, "label": label}
        )
        return TokenInfo(**out).token

    # -- design reviews --------------------------------------------------------------------

    async def start_review(
        self,
        model: str | ModelInfo,
        *,
        title: str = "review",
        camera: CameraState | dict[str, Any] | None = None,
        quality: dict[str, Any] | None = None,
        ttl: float = 7 * 24 * 3600.0,
    ) -> dict[str, Any]:
        """Starts a design review of a model: `presenter_url` and `join_url` (the page's
        links to open and to send), their tokens, and `review` (id, expiry). The shared
        view starts at `camera` (a live view's `camera` will do) with `quality`; without
        a camera, at the first participant's."""
        body: dict[str, Any] = {"model": _model_id(model), "title": title, "ttl_seconds": ttl}
        if camera is not None:
            cam = camera.model_dump() if isinstance(camera, CameraState) else dict(camera)
            body["view"] = {"camera": cam, **({"quality": quality} if quality else {})}
        elif quality:
            raise ValueError("a review's starting quality goes with a starting camera")
        return await self._json("POST", "/api/reviews", json=body)

    # -- views saved with a model ------------------------------------------------------------

    async def model_views(self, model: str | ModelInfo) -> list[dict[str, Any]]:
        """Views saved with a model (the page's Views panel), oldest first: `id`, `name`,
        `camera`, `sections`, `highlight`; `AsyncView.show` goes to one."""
        return list((await self._json("GET", f"/api/models/{_model_id(model)}/views"))["views"])

    async def save_model_view(
        self,
        model: str | ModelInfo,
        name: str,
        *,
        camera: CameraState | dict[str, Any],
        sections: Sequence[Plane] = (),
        highlight: Sequence[int] = (),
    ) -> dict[str, Any]:
        """Saves a view with a model, for everyone who views it (needs the API key):
        `camera` (a live view's `camera` will do), section planes, highlighted parts."""
        body = {
            "name": name,
            "camera": camera.model_dump() if isinstance(camera, CameraState) else dict(camera),
            "sections": section_planes(sections),
            "highlight": [int(p) for p in highlight],
        }
        return dict(await self._json("POST", f"/api/models/{_model_id(model)}/views", json=body))

    async def delete_model_view(self, model: str | ModelInfo, view_id: str) -> None:
        await self._json("DELETE", f"/api/models/{_model_id(model)}/views/{view_id}")

    async def review(self, review_id: str) -> dict[str, Any]:
        """A review: its model, who is in it now, where its shared view is (`view`),
        annotations and saved views."""
        return await self._json("GET", f"/api/reviews/{review_id}")

    # -- jobs ------------------------------------------------------------------------------

    async def build(
        self,
        source: str,
        *,
        name: str | None = None,
        memory: str | int | None = None,
        threads: int | None = None,
        layout: str | None = None,
        quantized_splits: bool | None = None,
        quantized_vertices: bool | None = None,
        compact_triangles: bool | None = None,
        tier_width: float | None = None,
        traversal_cost: float | None = None,
        lz4_hc_level: int | None = None,
        voxel_errors: bool | None = None,
        up: tuple[float, float, float] | None = None,
    ) -> JobInfo:
        """Queues a build of 'demo', 'scene:NAME:TRIANGLES:SEED' or a mesh in the data
        directory; wait for it with `wait`. `layout`: what the file is for, "balanced" (the
        default: tiered, far views read least), "smaller" (compact triangle blocks) or
        "smallest" (34-39 % of balanced; vastray/layouts.py). The options after it override
        the layout's (None: the layout's value): `quantized_splits`: the smaller node layout
        with the same images (docs/FORMAT.md §8); `quantized_vertices`: vertices on a grid of
        the model's box, smaller and lossy by at most a grid step (§11); `compact_triangles`:
        bit-packed triangle blocks, about 30 % smaller and lossless, full-detail frames a few
        per cent slower (§11a); `tier_width`: octaves of LOD radius per coarseness tier
        (default 1; 0: untiered, smaller and faster to build, far views read more; §15);
        `traversal_cost`: the kd-tree's SAH cost of a node step (default 4; higher: a coarser
        tree, faster to build and smaller, LOD frames nearer full detail at a PoE);
        `lz4_hc_level`: LZ4 HC for the blocks (1-12; default 0, LZ4's fast compressor): the same
        format, read as fast, smaller, a slower build; `voxel_errors`: LOD tests compare a bound
        on how far a voxel's box lies from its triangles, not the box's size (default on with
        quantized splits; §15). `up`: which way is up in the model (default +y; a z-up
        mesh takes (0, 0, 1)), as `update_model` sets it."""
        chosen = {
            "layout": layout,
            "quantized_splits": quantized_splits,
            "quantized_vertices": quantized_vertices,
            "compact_triangles": compact_triangles,
            "tier_width": tier_width,
            "traversal_cost": traversal_cost,
            "lz4_hc_level": lz4_hc_level,
            "voxel_errors": voxel_errors,
        }
        options = {"memory": memory, "threads": threads, **{k: v for k, v in chosen.items() if v is not None}}
        body = {"source": source, "name": name, "options": options, "up": up}
        return JobInfo(**await self._json("POST", "/api/jobs", json=body))

    async def job(self, job: str | JobInfo) -> JobInfo:
        return JobInfo(**await self._json("GET", f"/api/jobs/{job.id if isinstance(job, JobInfo) else job}"))

    async def jobs(self) -> list[JobInfo]:
        return [JobInfo(**j) for j in await self._json("GET", "/api/jobs")]

    async def cancel(self, job: str | JobInfo) -> JobInfo:
        return JobInfo(
            **await self._json("POST", f"/api/jobs/{job.id if isinstance(job, JobInfo) else job}/cancel")
        )

    async def job_events(self, job: str | JobInfo) -> AsyncIterator[JobInfo]:
        """The job after every change (server-sent events), to its end."""
        job_id = job.id if isinstance(job, JobInfo) else job
        async with self._http.stream("GET", f"/api/jobs/{job_id}/events", timeout=None) as r:
            if not r.is_success:
                await r.aread()
                raise_for_error(r)
            kind = None
            async for line in r.aiter_lines():
                if line.startswith("event: "):
                    kind = line[7:]
                elif line.startswith("data: ") and kind in ("progress", "end"):
                    info = JobInfo(**json.loads(line[6:]))
                    yield info
                    if kind == "end":
                        return
                elif line.startswith("data: ") and kind == "shutdown":
                    raise VastrayError(503, "shutting_down", "the server shut down during the build")

    async def wait(
        self,
        job: str | JobInfo,
        *,
        progress: bool | Callable[[JobInfo], None] = False,
        timeout: float | None = None,
    ) -> JobInfo:
        """Follows a job to its end; `progress=True` draws a progress bar, a callable
        hears every change. Raises BuildFailedError unless it succeeded."""
        bar = _ProgressBar() if progress is True else None
        hear = progress if callable(progress) else (bar.update if bar else None)
        deadline = None if timeout is None else time.monotonic() + timeout
        final: JobInfo | None = None
        try:
            async for info in self.job_events(job):
                if hear is not None:
                    hear(info)
                final = info
                if deadline is not None and time.monotonic() > deadline:
                    raise TimeoutError(f"job {info.id} not finished after {timeout} s")
        finally:
            if bar is not None:
                bar.close()
        assert final is not None
        if final.state not in TERMINAL_JOB_STATES:
            final = await self.job(final.id)
        if final.state != "succeeded":
            raise BuildFailedError(final)
        return final

    # -- rendering -------------------------------------------------------------------------

    async def render(
        self,
        model: str | ModelInfo,
        *,
        camera: dict[str, Any] | None = None,
        quality: dict[str, Any] | None = None,
        sections: Sequence[Plane] | None = None,
        format: str = "png",
        jpeg_quality: int = 90,
        timeout: float = 60.0,
    ) -> Frame:
        """One image, full detail unless `quality` says otherwise, cut by `sections`."""
        body: dict[str, Any] = {"format": format, "jpeg_quality": jpeg_quality, "timeout": timeout}
        if camera is not None:
            body["camera"] = camera
        if sections is not None:
            body["sections"] = section_planes(sections)
        if quality is not None:
            body["quality"] = quality
        r = await self._http.post(f"/api/models/{_model_id(model)}/render", json=body, timeout=timeout + 30)
        raise_for_error(r)
        stats = json.loads(r.headers.get("x-vastray-stats", "{}"))
        stats["frames"] = int(r.headers.get("x-vastray-frames", "1"))
        stats["seconds"] = float(r.headers.get("x-vastray-render-ms", "0")) / 1000
        return Frame(decode_image(r.content), None, stats, r.content, time.time())

    async def pick(
        self,
        model: str | ModelInfo,
        *,
        points: list[tuple[float, float]] | None = None,
        camera: dict[str, Any] | None = None,
        rays: list[tuple[tuple[float, float, float], tuple[float, float, float]]] | None = None,
        sections: Sequence[Plane] | None = None,
        timeout: float = 10.0,
    ) -> list[PickHit]:
        """Full-detail hits of image points of `camera`, or of world rays, in the model
        as `sections` cut it."""
        body: dict[str, Any] = {"timeout": timeout}
        if points is not None:
            body.update(points=points, camera=camera or {})
        if rays is not None:
            body["rays"] = rays
        if sections is not None:
            body["sections"] = section_planes(sections)
        out = await self._json("POST", f"/api/models/{_model_id(model)}/pick", json=body)
        return [PickHit(**h) for h in out["hits"]]

    def view(self, model: str | ModelInfo, **kw: Any) -> Any:
        """A live view (streamed frames) of a model; `async with client.view(m) as v:`."""
        from vastray.client.stream import AsyncView

        return AsyncView(self.url, _model_id(model), key=self.key, **kw)

    async def join(self, review: str | None = None, *, name: str | None = None, **kw: Any) -> Any:
        """A live view in a design review (by default the one the client's link names):
        a follower's frames are the presenter's view, and its `camera` follows theirs;
        `follow(False)` gives it a view of its own. `async with await client.join() as v:`."""
        review_id = review or self.review_id
        if review_id is None:
            raise ValueError("which review? pass its id, or make the client from a review's link")
        info = await self.review(review_id)
        return self.view(info["model"], review=review_id, name=name, **kw)


class _ProgressBar:
    """A tqdm bar over a job's percent, its phase as the label."""

    def __init__(self) -> None:
        from tqdm import tqdm

        self.bar = tqdm(total=100.0, unit="%", bar_format="{desc} {bar} {n:.0f}% [{elapsed}<{remaining}]")

    def update(self, info: JobInfo) -> None:
        self.bar.set_description_str(f"{info.name}: {info.phase or info.state}", refresh=False)
        self.bar.update(info.percent - self.bar.n)

    def close(self) -> None:
        self.bar.close()
