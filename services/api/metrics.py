"""Prometheus metrics of one API process (its own registry, so several apps can live in one process)."""

from __future__ import annotations

from prometheus_client import (CONTENT_TYPE_LATEST, CollectorRegistry, Counter, Histogram, disable_created_metrics,
                               generate_latest)
from prometheus_client.core import GaugeMetricFamily

from services.jobs import STATES, Jobs

disable_created_metrics()  # the *_created series only add noise to a scrape


class _JobStates:
    """Jobs by state, counted from the store when scraped (the store is the truth, not this process)."""

    def __init__(self, jobs: Jobs):
        self.jobs = jobs

    def collect(self):
        g = GaugeMetricFamily("kneemesh_jobs", "Jobs in the store by state.", labels=["state"])
        counts = dict.fromkeys(STATES, 0)
        for rec in self.jobs.all():
            counts[self.jobs.state(rec, self.jobs.steps(rec))] += 1
        for state, n in counts.items():
            g.add_metric([state], n)
        yield g


class Metrics:
    content_type = CONTENT_TYPE_LATEST

    def __init__(self, jobs: Jobs):
        self.registry = CollectorRegistry()
        self._requests = Counter("kneemesh_http_requests", "HTTP requests.", ["method", "route", "status"],
                                 registry=self.registry)
        self._latency = Histogram("kneemesh_http_request_seconds", "HTTP request latency.", ["route"],
                                  registry=self.registry)
        self._submitted = Counter("kneemesh_jobs_submitted", "Jobs queued.", registry=self.registry)
        self._rejected = Counter("kneemesh_requests_rejected", "Requests refused, by error code.", ["code"],
                                 registry=self.registry)
        self._bytes = Counter("kneemesh_upload_bytes", "Bytes of uploads received.", registry=self.registry)
        self.registry.register(_JobStates(jobs))

    def request(self, method: str, route: str, status: int, seconds: float) -> None:
        self._requests.labels(method, route, str(status)).inc()
        self._latency.labels(route).observe(seconds)

    def submitted(self) -> None:
        self._submitted.inc()

    def rejected(self, code: str) -> None:
        self._rejected.labels(code).inc()

    def uploaded(self, n_bytes: int) -> None:
        self._bytes.inc(n_bytes)

    def render(self) -> bytes:
        return generate_latest(self.registry)
