"""Server configuration: flags of `vastray serve`, or VASTRAY_* environment variables,
or the defaults, which work with no configuration at all."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Annotated

from pydantic import Field, field_validator
from pydantic_settings import BaseSettings, NoDecode, SettingsConfigDict

from vastray.units import parse_bytes


def _split(value: object) -> object:
    # Lists from the environment are comma-separated ("a,b"), not JSON.
    if isinstance(value, str):
        return [v.strip() for v in value.split(",") if v.strip()]
    return value


def usable_cores() -> int:
    """Cores this process may run on (a container's or taskset's CPU set, not the host's)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        return os.cpu_count() or 1


def default_render_workers() -> int:
    """Frames in flight at once: 2 up to 5 cores (one frame encodes while the next
    renders), half the cores beyond. A frame's tile loop uses every core, but its encode
    and its serial work do not; with many viewers on many cores two in flight leave cores
    idle (16 viewers on 16 cores: 18.9 Mpixel/s with 2, 31.1 with 8;
    bench/results/stream-16-workers.md)."""
    return max(2, min(64, usable_cores() // 2))


class Settings(BaseSettings):
    model_config = SettingsConfigDict(env_prefix="VASTRAY_", extra="ignore")

    data_dir: Path = Field(Path("data"), description="where the registry, models, uploads and jobs live")
    host: str = "127.0.0.1"
    port: int = Field(8000, ge=0, le=65535)
    public_url: str | None = Field(None, description="the URL people open, when behind a proxy")

    cache: int = Field(1 << 30, description="block cache budget in bytes (e.g. 1G)")
    render_threads: int = Field(0, ge=0, description="threads per frame; 0: every core")
    fetchers: int = Field(2, ge=1, le=64, description="block fetcher threads")
    render_workers: int = Field(
        default_factory=default_render_workers,
        ge=1,
        le=64,
        description="frames rendered or encoded at once (default: 2, or half the cores beyond 5)",
    )

    api_keys: Annotated[list[str], NoDecode] = Field(
        default_factory=list, description="keys for write endpoints"
    )
    cors_origins: Annotated[list[str], NoDecode] = Field(default_factory=list)

    upload_limit: int = Field(4 << 30, description="largest upload in bytes")
    max_message_bytes: int = Field(1 << 20, description="largest JSON request or message")
    max_pixels: int = Field(3840 * 2160, ge=1, description="pixel budget of one image (width x height)")
    request_rate: float = Field(30.0, gt=0, description="render/pick requests per second per client")
    render_timeout: float = Field(120.0, gt=0, description="longest one-shot render a client may ask for")
    client_timeout: float = Field(
        60.0, gt=0, description="a viewer silent this long is closed (clients ping)"
    )
    ws_ping_interval: float = Field(
        20.0, gt=0, description="WebSocket pings: a client that stops answering is reaped"
    )

    build_jobs: int = Field(1, ge=1, le=64, description="build jobs run at once")
    build_memory: int = Field(2 << 30, description="memory budget of one build job")
    build_threads: int = Field(0, ge=0, description="threads per build job; 0: every core")
    build_memory_limit: int = Field(0, ge=0, description="largest budget a job may ask for; 0: build_memory")
    build_rss_slack: float = Field(
        1.25,
        gt=0,
        description="a worker is stopped when its resident memory passes (budget + fixed overhead) x this",
    )

    demo: bool = Field(True, description="build the demo model when the data directory is new")

    @field_validator("cache", "upload_limit", "build_memory", "max_message_bytes", mode="before")
    @classmethod
    def _bytes(cls, value: object) -> object:
        if isinstance(value, str):
            return parse_bytes(value)
        return value

    @field_validator("build_memory_limit", mode="before")
    @classmethod
    def _bytes_or_zero(cls, value: object) -> object:
        if isinstance(value, str):
            return 0 if value.strip() == "0" else parse_bytes(value)
        return value

    @field_validator("api_keys", "cors_origins", mode="before")
    @classmethod
    def _lists(cls, value: object) -> object:
        return _split(value)

    @field_validator("api_keys")
    @classmethod
    def _keys(cls, keys: list[str]) -> list[str]:
        for k in keys:
            if len(k) < 16:
                raise ValueError("API keys must be at least 16 characters (use a random one)")
        return keys

    @property
    def job_memory_limit(self) -> int:
        return self.build_memory_limit or self.build_memory
