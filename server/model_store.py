"""The models the server serves: their files under `models/`, their registry rows, and
the one block cache every model and viewer shares.

A model is opened in the cache when first used and stays open while it is in use.
Renders, picks, viewers and jobs hold a lease on it; deleting a model in use marks it
`deleting` (it disappears from listings and takes no new leases) and removes the file
when the last lease ends, so a delete never breaks a viewer.
"""

from __future__ import annotations

import logging
import os
import secrets
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from vastray.camera import Y_UP, Vec3
from vastray.modelfile import FLAG_COLOURS, FLAG_PART_IDS, ModelError, ModelFile
from vastray.outofcore import OutOfCoreModel, make_cache
from vastray.schemas import LevelInfo, ModelInfo
from vastray.server.errors import ApiError
from vastray.server.registry import JobRow, ModelRow, Registry
from vastray.sources import MODEL_SUFFIX

log = logging.getLogger("vastray.models")


def new_id(prefix: str) -> str:
    return f"{prefix}-{secrets.token_hex(6)}"


def describe_file(path: Path) -> dict[str, Any]:
    """What `inspect` says of a model file, for the registry (raises ModelError)."""
    with ModelFile(path) as f:
        stats = f.stats()
        flags = f.header["flags"]
        part_count = len(f.parts)
    lo, hi = stats["bounds"]
    return {
        "triangles": stats["triangles"],
        "input_triangles": stats["input_triangles"],
        "degenerate": stats["degenerate"],
        "bytes": stats["file_bytes"],
        "bounds": [list(lo), list(hi)],
        "lod_levels": len(stats["levels"]) - 1,
        "colours": bool(flags & FLAG_COLOURS),
        "part_ids": bool(flags & FLAG_PART_IDS),
        "part_count": part_count,
        "format_version": stats["version"],
        "up_in_file": stats["up"],  # as its builder was told (None: not said)
        "levels": [
            {k: lv.get(k) for k in ("level", "blocks", "raw_bytes", "stored_bytes", "nodes", "voxels")}
            for lv in stats["levels"]
        ],
    }


class ModelStore:
    def __init__(self, registry: Registry, data_dir: Path, *, cache_bytes: int, fetchers: int) -> None:
        self.registry = registry
        self.data_dir = data_dir
        self.models_dir = data_dir / "models"
        self.models_dir.mkdir(parents=True, exist_ok=True)
        self.cache = make_cache(cache_bytes, fetchers)
        self._lock = threading.Lock()
        self._open: dict[str, OutOfCoreModel] = {}
        self._leases: dict[str, int] = {}

    # -- reading ---------------------------------------------------------------------------

    def info(self, row: ModelRow) -> ModelInfo:
        i = row.info
        with self._lock:
            in_use = self._leases.get(row.id, 0)
        return ModelInfo(
            id=row.id,
            name=row.name,
            state=row.state,
            created_at=row.created_at,
            source=row.source,
            job_id=row.job_id,
            file=row.file,
            triangles=i.get("triangles"),
            input_triangles=i.get("input_triangles"),
            degenerate=i.get("degenerate"),
            bytes=i.get("bytes"),
            bounds=i.get("bounds"),
            lod_levels=i.get("lod_levels"),
            colours=i.get("colours"),
            part_ids=i.get("part_ids"),
            part_count=i.get("part_count", 0),
            levels=[LevelInfo(**lv) for lv in i.get("levels", [])] or None,
            build=i.get("build"),
            in_use=in_use,
            up=row.up or Y_UP,
            units=row.units,
        )

    def row(self, model_id: str, *, ready: bool = False) -> ModelRow:
        row = self.registry.model(model_id)
        if row is None or row.state == "deleting":
            raise ApiError(404, "model_not_found", f"no model {model_id!r}")
        if ready and row.state != "ready":
            raise ApiError(
                409, "model_not_ready", f"model {model_id} is still being built (job {row.job_id})"
            )
        return row

    @contextmanager
    def lease(self, model_id: str) -> Iterator[OutOfCoreModel]:
        """The model, open in the shared cache, for as long as the `with` lasts."""
        model = self.acquire(model_id)
        try:
            yield model
        finally:
            self.release(model_id)

    def acquire(self, model_id: str) -> OutOfCoreModel:
        row = self.row(model_id, ready=True)
        with self._lock:
            model = self._open.get(model_id)
            if model is None:
                try:
                    model = OutOfCoreModel(self.data_dir / str(row.file), self.cache)
                    # Read here, off the event loop: welcomes, picks and views use it.
                    model.part_table  # noqa: B018
                except ModelError as exc:
                    raise ApiError(
                        500, "model_damaged", f"model {model_id} cannot be opened: {exc}"
                    ) from None
                self._open[model_id] = model
            self._leases[model_id] = self._leases.get(model_id, 0) + 1
            return model

    def release(self, model_id: str) -> None:
        with self._lock:
            left = self._leases.get(model_id, 1) - 1
            if left > 0:
                self._leases[model_id] = left
                return
            self._leases.pop(model_id, None)
        row = self.registry.model(model_id)
        if row is not None and row.state == "deleting":
            self._remove(row)

    def in_use(self, model_id: str) -> int:
        with self._lock:
            return self._leases.get(model_id, 0)

    # -- changing --------------------------------------------------------------------------

    def register_file(self, source: Path, name: str, *, move: bool, up: Vec3 | None = None) -> ModelRow:
        """A built model already on disk becomes a served model: moved into models/
        (uploads), or served where it is (a file the user put in the data directory,
        which deleting the model then leaves alone). ApiError 422 if it is no model."""
        try:
            info = describe_file(source)
        except ModelError as exc:
            raise ApiError(422, "invalid_model", str(exc)) from None
        if up is None and info["up_in_file"]:
            up = (info["up_in_file"][0], info["up_in_file"][1], info["up_in_file"][2])
        model_id = new_id("mdl")
        target = source
        if move:
            target = self.models_dir / f"{model_id}{MODEL_SUFFIX}"
            os.replace(source, target)
        info["owned"] = move
        row = ModelRow(
            model_id,
            name,
            "ready",
            str(target.resolve().relative_to(self.data_dir.resolve())),
            source.name,
            None,
            time.time(),
            info,
            up,
        )
        self.registry.add_model(row)
        log.info("model %s (%s): registered, %s triangles", model_id, name, f"{info['triangles']:,}")
        return row

    def patch(
        self, model_id: str, *, name: str | None = None, up: Vec3 | None = None, units: str | None = None
    ) -> ModelRow:
        """A model renamed, given its up or its units ("" for none; a model being built
        may be, too: the build touches none of them)."""
        self.row(model_id)
        fields: dict[str, Any] = {k: v for k, v in (("name", name), ("up", up)) if v is not None}
        if units is not None:
            fields["units"] = units or None
        if fields:
            self.registry.update_model(model_id, **fields)
            log.info("model %s: %s", model_id, ", ".join(f"{k} set to {v}" for k, v in fields.items()))
        return self.row(model_id)

    def reserve(self, name: str, source: str, job_id: str, up: Vec3 | None = None) -> ModelRow:
        """A model that a build job will make: listed as building until it is done."""
        row = ModelRow(new_id("mdl"), name, "building", None, source, job_id, time.time(), {}, up)
        self.registry.add_model(row)
        return row

    def publish(self, job: JobRow, built: Path, report: dict[str, Any]) -> str | None:
        """A finished build: moved into models/ and made ready (unless it was deleted
        while it was built, then it is dropped)."""
        assert job.model_id is not None
        row = self.registry.model(job.model_id)
        if row is None or row.state == "deleting":
            built.unlink(missing_ok=True)
            if row is not None:
                self.registry.delete_model(row.id)
            return None
        info = describe_file(built)
        info["build"] = {
            "options": {k: v for k, v in job.options.items() if k != "scratch_dir"},
            "report": {k: report.get(k) for k in BUILD_REPORT_FIELDS if k in report},
        }
        target = self.models_dir / f"{row.id}{MODEL_SUFFIX}"
        os.replace(built, target)
        self.registry.update_model(
            row.id, state="ready", file=str(target.relative_to(self.data_dir)), info=info
        )
        log.info("model %s (%s): built, %s triangles", row.id, row.name, f"{info['triangles']:,}")

    def discard(self, job: JobRow) -> None:
        """A build that did not finish: its reserved model goes."""
        if job.model_id is None:
            return
        row = self.registry.model(job.model_id)
        if row is not None and row.state in ("building", "deleting") and row.file is None:
            self.registry.delete_model(row.id)

    def delete(self, model_id: str) -> bool:
        """True if the model is gone now, False if it goes when its last user leaves."""
        row = self.row(model_id)
        self.registry.update_model(model_id, state="deleting")
        if row.state == "building":
            return False  # the job's end drops it
        if self.in_use(model_id):
            log.info("model %s: delete deferred until %d user(s) leave", model_id, self.in_use(model_id))
            return False
        self._remove(self.registry.model(model_id) or row)
        return True

    def _remove(self, row: ModelRow) -> None:
        with self._lock:
            if self._leases.get(row.id):
                return
            model = self._open.pop(row.id, None)
        if model is not None:
            model.close()
        if row.file and row.info.get("owned", True):
            (self.data_dir / row.file).unlink(missing_ok=True)
        self.registry.delete_model(row.id)
        log.info("model %s (%s): deleted", row.id, row.name)

    def close(self) -> None:
        with self._lock:
            models = list(self._open.values())
            self._open.clear()
        for m in models:
            m.close()


# What of a build report is kept with the model (the rest is in the job).
BUILD_REPORT_FIELDS = (
    "input",
    "triangles",
    "input_triangles",
    "degenerate",
    "file_bytes",
    "bytes_per_triangle",
    "compression_ratio",
    "node_levels",
    "blocks",
    "parts",
    "seconds",
    "phase_seconds",
    "triangles_per_second",
    "peak_rss_bytes",
    "warnings",
)
