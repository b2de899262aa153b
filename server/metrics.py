"""Prometheus metrics (prometheus_client), served as text at /metrics.

Counters and histograms are updated where frames are made; the block cache and the job
table are read when Prometheus scrapes (a custom collector), so they cost nothing
between scrapes."""

from __future__ import annotations

from collections.abc import Callable, Iterable
from typing import Any

from prometheus_client import CollectorRegistry, Counter, Gauge, Histogram, generate_latest
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily
from prometheus_client.registry import Collector

from vastray import native

# Frame times from a few ms (small views, LOD) to the longest full-detail renders.
FRAME_BUCKETS = (
    0.005,
    0.01,
    0.02,
    0.035,
    0.05,
    0.075,
    0.1,
    0.15,
    0.25,
    0.5,
    1.0,
    2.5,
    5.0,
    10.0,
    30.0,
    120.0,
)
# Input-to-frame latency: the users' bounds are 0.1 s (display) and 0.25 s (selection).
LATENCY_BUCKETS = (0.01, 0.02, 0.03, 0.05, 0.075, 0.1, 0.15, 0.25, 0.5, 1.0, 2.5)
JOB_STATES = ("queued", "running", "succeeded", "failed", "cancelled", "interrupted")


class _LiveCollector(Collector):
    """The cache's totals and the job table, read at scrape time."""

    def __init__(
        self,
        cache: native.BlockCache,
        job_counts: Callable[[], dict[str, int]],
        hit_rate: Callable[[], float],
        viewers: Callable[[], int],
    ) -> None:
        self.cache = cache
        self.job_counts = job_counts
        self.hit_rate = hit_rate
        self.viewers = viewers

    def collect(self) -> Iterable[Any]:
        t = self.cache.totals()
        yield GaugeMetricFamily("vastray_cache_budget_bytes", "Block cache budget", value=t["budget_bytes"])
        yield GaugeMetricFamily(
            "vastray_cache_resident_bytes", "Bytes of blocks in the cache", value=t["resident_bytes"]
        )
        yield GaugeMetricFamily(
            "vastray_cache_pending_blocks",
            "Blocks requested and not yet loaded",
            value=t["pending"] + t["loading"],
        )
        yield CounterMetricFamily(
            "vastray_cache_bytes_loaded", "Bytes read from model files by the fetchers", value=t["bytes_read"]
        )
        yield CounterMetricFamily("vastray_cache_blocks_evicted", "Blocks evicted", value=t["evicted"])
        yield CounterMetricFamily(
            "vastray_cache_blocks_failed", "Blocks that failed to load or verify", value=t["failed"]
        )
        yield GaugeMetricFamily(
            "vastray_cache_hit_ratio",
            "Share of block lookups found cached, since start",
            value=self.hit_rate(),
        )
        yield GaugeMetricFamily("vastray_models_open", "Models open in the cache", value=t["models"])
        yield GaugeMetricFamily("vastray_viewers", "Connected viewers", value=self.viewers())
        jobs = GaugeMetricFamily("vastray_jobs", "Build jobs by state", labels=["state"])
        counts = self.job_counts()
        for state in JOB_STATES:
            jobs.add_metric([state], counts.get(state, 0))
        yield jobs


class Metrics:
    def __init__(self) -> None:
        self.registry = CollectorRegistry()
        r = self.registry
        self.frames = Counter("vastray_frames", "Frames rendered and encoded", ["kind"], registry=r)
        # Frames sent: a review's shared frame is rendered once and sent to every follower.
        self.frames_sent = Counter("vastray_frames_sent", "Frames sent to clients", ["kind"], registry=r)
        self.frame_seconds = Histogram(
            "vastray_frame_seconds", "Render time of a frame", ["kind"], buckets=FRAME_BUCKETS, registry=r
        )
        self.encode_seconds = Histogram(
            "vastray_encode_seconds", "Encode time of a frame", ["kind"], buckets=FRAME_BUCKETS, registry=r
        )
        self.latency = Histogram(
            "vastray_input_to_frame_seconds",
            "From a camera message's arrival to its frame's send",
            buckets=LATENCY_BUCKETS,
            registry=r,
        )
        self.bytes_sent = Counter("vastray_bytes_sent", "Image bytes sent", ["kind"], registry=r)
        self.pick_seconds = Histogram(
            "vastray_pick_seconds", "Pick requests, full detail", buckets=LATENCY_BUCKETS, registry=r
        )
        self.working_set = Gauge(
            "vastray_working_set_bytes", "Working set of the last frame rendered", registry=r
        )
        self.lookups = Counter("vastray_cache_lookups", "Block lookups by frames", registry=r)
        self.lookup_hits = Counter("vastray_cache_lookup_hits", "Block lookups found cached", registry=r)
        self.http_requests = Counter(
            "vastray_http_requests", "HTTP requests by route and status", ["route", "status"], registry=r
        )
        self._lookups = 0.0
        self._hits = 0.0

    def attach(
        self, cache: native.BlockCache, job_counts: Callable[[], dict[str, int]], viewers: Callable[[], int]
    ) -> None:
        self.registry.register(_LiveCollector(cache, job_counts, self.hit_rate, viewers))

    def hit_rate(self) -> float:
        return self._hits / self._lookups if self._lookups else 1.0

    def frame_rendered(self, kind: str, stats: native.FrameStats, encode_seconds: float) -> None:
        self.frames.labels(kind).inc()
        self.frame_seconds.labels(kind).observe(stats.milliseconds / 1000.0)
        self.encode_seconds.labels(kind).observe(encode_seconds)
        self.working_set.set(stats.working_set_bytes)
        self.lookups.inc(stats.lookups)
        self.lookup_hits.inc(stats.lookups * stats.cache_hit_rate)
        self._lookups += stats.lookups
        self._hits += stats.lookups * stats.cache_hit_rate

    def render(self) -> bytes:
        return generate_latest(self.registry)
