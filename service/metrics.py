"""Prometheus metrics (`prometheus_client`), one registry per app (tests build many apps).

Exposed on GET /metrics in the text format:

    nemsim_http_requests_total{method, route, status}     counter
    nemsim_http_request_duration_seconds{route}            histogram (route = the path template)
    nemsim_queue_depth{work}, nemsim_running{work}         gauges per admission gate (rollouts, meshes,
                                                           mechanisms), read when scraped
    nemsim_cache_requests_total{kind, result}              counter, result = hit | miss
    nemsim_rollouts_total                                  counter of computed rollouts (rate() = per second)
    nemsim_rollout_compute_seconds                         histogram of the model time per computed rollout
    nemsim_model_ready                                     gauge, 1 once the model serves
"""

from __future__ import annotations

from typing import Any

from prometheus_client import (
    CONTENT_TYPE_LATEST,
    CollectorRegistry,
    Counter,
    Gauge,
    Histogram,
    generate_latest,
)

LATENCY_BUCKETS = (0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1, 2.5, 5, 10, 30, 60, 120)


class Metrics:
    content_type = CONTENT_TYPE_LATEST

    def __init__(self) -> None:
        self.registry = CollectorRegistry()
        r = self.registry
        self.requests = Counter(
            "nemsim_http_requests", "HTTP requests answered", ["method", "route", "status"], registry=r
        )
        self.latency = Histogram(
            "nemsim_http_request_duration_seconds",
            "HTTP request latency",
            ["route"],
            buckets=LATENCY_BUCKETS,
            registry=r,
        )
        self.queue = Gauge("nemsim_queue_depth", "requests waiting for a slot", ["work"], registry=r)
        self.running = Gauge("nemsim_running", "requests holding a slot", ["work"], registry=r)
        self.cache = Counter("nemsim_cache_requests", "cache look-ups", ["kind", "result"], registry=r)
        self.rollouts = Counter("nemsim_rollouts", "rollouts computed (not from the cache)", registry=r)
        self.rollout_seconds = Histogram(
            "nemsim_rollout_compute_seconds",
            "model time per computed rollout",
            buckets=LATENCY_BUCKETS,
            registry=r,
        )
        self.ready = Gauge("nemsim_model_ready", "1 once the model is loaded and warmed up", registry=r)

    def observe_request(self, method: str, route: str, status: int, seconds: float) -> None:
        self.requests.labels(method, route, str(status)).inc()
        self.latency.labels(route).observe(seconds)

    def cache_lookup(self, kind: str, hit: bool) -> None:
        self.cache.labels(kind, "hit" if hit else "miss").inc()

    def rollout_computed(self, seconds: float) -> None:
        self.rollouts.inc()
        self.rollout_seconds.observe(seconds)

    def render(self, gates: Any, ready: bool) -> bytes:
        for gate in gates.all():
            self.queue.labels(gate.name).set(gate.waiting)
            self.running.labels(gate.name).set(gate.active)
        self.ready.set(1.0 if ready else 0.0)
        return generate_latest(self.registry)
