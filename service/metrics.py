"""Prometheus metrics of one app instance (own registry, so several apps can live in a process)."""

from __future__ import annotations

from functools import partial

from prometheus_client import CONTENT_TYPE_LATEST as CONTENT_TYPE  # noqa: F401  (re-export)
from prometheus_client import (
    CollectorRegistry,
    Counter,
    Gauge,
    Histogram,
    disable_created_metrics,
    generate_latest,
)

# Seconds per frame stage: 64x48 test frames take ~1 ms, 4K frames several seconds.
_BUCKETS = (0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 30.0)


class Metrics:
    def __init__(self) -> None:
        disable_created_metrics()  # the *_created series only add noise to every scrape
        self.registry = CollectorRegistry()
        # Every metric lives in this app's registry, not the process-wide default one.
        counter = partial(Counter, registry=self.registry)
        gauge = partial(Gauge, registry=self.registry)
        self.frames = counter("quietframe_frames", "Frames denoised", ["model", "reset"])
        self.replays = counter(
            "quietframe_frame_replays", "Idempotent retries answered from the last reply"
        )
        self.latency = Histogram(
            "quietframe_frame_seconds", "Time per frame by stage", ["stage"],
            buckets=_BUCKETS, registry=self.registry,
        )
        self.sessions = gauge("quietframe_sessions", "Open sessions")
        self.sessions_created = counter("quietframe_sessions_created", "Sessions created")
        self.sessions_closed = counter("quietframe_sessions_closed", "Sessions ended", ["reason"])
        self.history_bytes = gauge(
            "quietframe_history_bytes", "State and last replies held in memory"
        )
        self.bytes_in = counter("quietframe_request_bytes", "EXR bytes received")
        self.bytes_out = counter("quietframe_response_bytes", "EXR bytes sent")
        self.sanitized = counter(
            "quietframe_sanitized_values", "Input values replaced by the sanitising rule",
            ["buffer"],
        )
        self.choices = counter(
            "quietframe_auto_choices",
            "Models chosen by model=auto (a session's first frame and each cut)",
            ["model", "quality", "noise_source"],
        )
        self.errors = counter("quietframe_errors", "Error responses", ["status", "code"])
        # Load, read at each scrape (observe_load): what the autoscaler scales on
        # (deploy/k8s/autoscaler.yaml, through prometheus-adapter).
        self.frames_in_flight = gauge(
            "quietframe_frames_in_flight",
            "Frames being received or denoised (waiting for a worker included)",
        )
        self.frame_slots = gauge(
            "quietframe_frame_slots", "Frames denoised at once (QUIETFRAME_WORKERS)"
        )
        self.memory_reserved = gauge(
            "quietframe_memory_reserved_bytes",
            "Memory budget reserved by frames in flight (QUIETFRAME_MEMORY_BUDGET_MB)",
        )

    def count_error(self, status: int, code: str) -> None:
        self.errors.labels(str(status), code).inc()

    def observe_load(self, frames_in_flight: int, frame_slots: int, reserved_bytes: int) -> None:
        self.frames_in_flight.set(frames_in_flight)
        self.frame_slots.set(frame_slots)
        self.memory_reserved.set(reserved_bytes)

    def render(self) -> bytes:
        return generate_latest(self.registry)
