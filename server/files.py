"""Files in the data directory: paths a client names (never outside the directory),
and uploads streamed to disk (never held in memory, never past the size limit, never
left half-written)."""

from __future__ import annotations

import asyncio
import os
import re
import secrets
import shutil
from collections.abc import AsyncIterator
from pathlib import Path

from vastray.server.errors import ApiError
from vastray.sources import MODEL_SUFFIX, is_model_file
from vastray.units import format_bytes

# Folders the server manages itself; clients name files elsewhere in the data directory.
INTERNAL = ("models", "jobs", "uploads")
MESH_SUFFIXES = (".obj", ".ply", ".stl", ".glb", ".gltf", ".off", ".f32")
DISK_RESERVE = 256 << 20  # free space an upload must leave on the disk
_SAFE_NAME = re.compile(r"[^A-Za-z0-9._-]+")


def inside(data_dir: Path, relative: str) -> Path:
    """The file `relative` names inside the data directory; ApiError 403 for a path
    that leaves it (absolute, `..`, or a link that points out), 404 if missing."""
    if not relative or relative.startswith(("/", "\\")) or "\x00" in relative:
        raise ApiError(403, "path_outside_data", f"{relative!r}: give a path relative to the data directory")
    root = data_dir.resolve()
    path = (root / relative).resolve()
    if not path.is_relative_to(root):
        raise ApiError(403, "path_outside_data", f"{relative!r} is outside the data directory")
    if path.relative_to(root).parts[:1] and path.relative_to(root).parts[0] in INTERNAL:
        raise ApiError(403, "path_outside_data", f"{relative!r} is in a folder the server manages")
    if not path.is_file():
        raise ApiError(404, "file_not_found", f"{relative!r}: no such file in the data directory")
    return path


def safe_filename(name: str) -> str:
    base = os.path.basename(name.replace("\\", "/")).strip()
    cleaned = _SAFE_NAME.sub("_", base).strip("._") or "upload"
    return cleaned[:120]


def kind_of(path: Path) -> str:
    """'model' for a built model (by its magic bytes), 'mesh' for a mesh format we read."""
    if is_model_file(path):
        return "model"
    if path.suffix.lower() == MODEL_SUFFIX:
        raise ApiError(422, "invalid_model", f"{path.name}: not a vastray model (bad magic bytes)")
    if path.suffix.lower() not in MESH_SUFFIXES:
        raise ApiError(
            415,
            "unsupported_format",
            f"{path.name}: unsupported file type; send a built model ({MODEL_SUFFIX}) or a mesh "
            f"({', '.join(MESH_SUFFIXES)})",
        )
    return "mesh"


class Uploads:
    def __init__(self, data_dir: Path, limit: int) -> None:
        self.dir = data_dir / "uploads"
        self.dir.mkdir(parents=True, exist_ok=True)
        self.limit = limit
        # Partial uploads of a server that stopped mid-transfer.
        for leftover in self.dir.glob("*/.partial-*"):
            leftover.unlink(missing_ok=True)

    def path(self, upload_id: str) -> Path:
        if not re.fullmatch(r"upl-[0-9a-f]{12}", upload_id):
            raise ApiError(404, "upload_not_found", f"no upload {upload_id!r}")
        folder = self.dir / upload_id
        files = [p for p in folder.iterdir() if not p.name.startswith(".")] if folder.is_dir() else []
        if not files:
            raise ApiError(404, "upload_not_found", f"no upload {upload_id!r}")
        return files[0]

    def check_room(self, declared: int | None) -> None:
        if declared is not None and declared > self.limit:
            raise ApiError(
                413,
                "upload_too_large",
                f"the upload is {format_bytes(declared)}; this server takes at most "
                f"{format_bytes(self.limit)}",
            )
        free = shutil.disk_usage(self.dir).free
        need = (declared or 0) + DISK_RESERVE
        if need > free:
            raise ApiError(
                507,
                "insufficient_storage",
                f"the data directory has {format_bytes(free)} free; this upload needs "
                f"{format_bytes(need)} with the reserve",
            )

    async def receive(
        self, filename: str, chunks: AsyncIterator[bytes], declared: int | None
    ) -> tuple[str, Path]:
        """Streams the body to `uploads/<id>/<filename>`; returns (id, path)."""
        self.check_room(declared)
        upload_id = f"upl-{secrets.token_hex(6)}"
        folder = self.dir / upload_id
        folder.mkdir()
        name = safe_filename(filename)
        partial = folder / f".partial-{name}"
        size = 0
        try:
            with open(partial, "wb") as f:
                async for chunk in chunks:
                    size += len(chunk)
                    if size > self.limit:
                        raise ApiError(
                            413,
                            "upload_too_large",
                            f"the upload passed {format_bytes(self.limit)}, this server's limit",
                        )
                    if declared is not None and size > declared:
                        raise ApiError(400, "bad_upload", "the body is longer than its Content-Length")
                    await asyncio.to_thread(f.write, chunk)  # the loop never waits on the disk
            if size == 0:
                raise ApiError(400, "empty_upload", f"{name}: the upload is empty")
            if declared is not None and size != declared:
                raise ApiError(400, "bad_upload", f"the body ended after {size} of {declared} bytes")
            final = folder / name
            os.replace(partial, final)
        except BaseException:
            shutil.rmtree(folder, ignore_errors=True)
            raise
        return upload_id, final

    def remove(self, upload_id: str) -> None:
        shutil.rmtree(self.dir / upload_id, ignore_errors=True)
