"""Prometheus metrics of one app instance (own registry, so several apps can coexist)."""

from __future__ import annotations

STAGES = ("parse", "preprocess", "queue", "embed", "search", "verify", "total")
_LATENCY_BUCKETS = (
    0.0005, 0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0,
)  # fmt: skip


class Metrics:
    """Request counts, latency histograms by stage, errors by kind, batch sizes."""

    def __init__(self) -> None:
        from prometheus_client import CollectorRegistry, Counter, Gauge, Histogram

        self.registry = CollectorRegistry()
        self.requests = Counter(
            "pnvlad_requests",
            "HTTP requests by route template and status code.",
            ["route", "method", "status"],
            registry=self.registry,
        )
        self.stage_seconds = Histogram(
            "pnvlad_stage_seconds",
            "Time per query spent in each stage (seconds).",
            ["stage"],
            buckets=_LATENCY_BUCKETS,
            registry=self.registry,
        )
        self.errors = Counter(
            "pnvlad_errors", "Error responses by kind.", ["kind"], registry=self.registry
        )
        self.batch_size = Histogram(
            "pnvlad_batch_size",
            "Clouds embedded together by the micro-batcher.",
            buckets=(1, 2, 4, 8, 16, 32, 64, 128),
            registry=self.registry,
        )
        self.index_vectors = Gauge(
            "pnvlad_index_vectors", "Vectors in the loaded index.", registry=self.registry
        )
        self.reloads = Counter(
            "pnvlad_reloads",
            "Map reloads (admin route or SIGHUP) by result: swapped, refused (the bundle failed "
            "its checks; the old one kept serving), busy (another reload was running).",
            ["result"],
            registry=self.registry,
        )
        self.disconnects = Counter(
            "pnvlad_client_disconnects",
            "Requests whose client went away before the body was complete.",
            registry=self.registry,
        )

    def observe(self, timings: dict[str, float]) -> None:
        """Record one query's stage timings (seconds)."""
        for stage, seconds in timings.items():
            if stage in STAGES:
                self.stage_seconds.labels(stage).observe(seconds)

    def render(self) -> tuple[bytes, str]:
        """The text exposition and its content type."""
        from prometheus_client import CONTENT_TYPE_LATEST, generate_latest

        return generate_latest(self.registry), CONTENT_TYPE_LATEST

    def error(self, kind: str) -> None:
        self.errors.labels(kind).inc()
